"""The ``gmjax`` command.

``gmjax`` with no arguments runs the default study (Xu et al. (PCM) Table 7 over 100 runs);
``gmjax study NAME``, ``gmjax reproduce [TABLE]``, ``gmjax static`` (the static reduction cases of Xu et al. (PCM)),
``gmjax bench NAME`` (``benchmarks/bench_NAME.py`` from a source checkout), ``gmjax --version``.

Studies run in float64 (the command turns on ``jax_enable_x64``; ``--float32`` keeps JAX's default),
and the header line says which. Every user error (a bad option value, an unwritable ``--out``) ends
with a one-line message on stderr and exit code 2; ``--json`` prints strict JSON (``null`` for an
undefined number such as the standard error of one run).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
from pathlib import Path
from typing import Sequence

import gmjax

_BENCH_DIR = Path(__file__).resolve().parent.parent / "benchmarks"


def _available_benchmarks() -> list[str]:
    if not _BENCH_DIR.is_dir():
        return []
    return sorted(p.stem[len("bench_") :] for p in _BENCH_DIR.glob("bench_*.py"))


def _run_bench(name: str, rest: Sequence[str]) -> int:
    names = _available_benchmarks()
    if not names:
        print(
            f"gmjax bench: no benchmarks/ folder next to the package ({_BENCH_DIR}); "
            "benchmarks run from a source checkout (pip install -e .)",
            file=sys.stderr,
        )
        return 2
    if name not in names:
        print(f"gmjax bench: unknown benchmark {name!r}; available: {', '.join(names)}", file=sys.stderr)
        return 2
    path = _BENCH_DIR / f"bench_{name}.py"
    spec = importlib.util.spec_from_file_location(f"gmjax_bench_{name}", path)
    assert spec is not None and spec.loader is not None  # the file exists: checked above
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(_BENCH_DIR))
    spec.loader.exec_module(module)
    module.main(list(rest))
    return 0


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gmjax",
        description=(
            "Gaussian-mixture state estimation in JAX. With no command, runs the default study: "
            "Xu et al. (PCM) Table 7 (NL-GSF, PCM-GSF, R-GSF with EKFs and a 300-particle PF, 100 runs)."
        ),
    )
    parser.add_argument("--version", action="version", version=f"gmjax {gmjax.__version__}")
    sub = parser.add_subparsers(dest="command")

    study = sub.add_parser("study", help="run a Monte Carlo study of a paper scenario")
    study.add_argument(
        "name", nargs="?", default="jump", help="study name (default: jump); 'list' lists them"
    )
    _add_study_args(study)

    repro = sub.add_parser("reproduce", help="reproduce a paper table; without TABLE, list them")
    repro.add_argument("table", nargs="?", help="e.g. seed000-table7")
    _add_study_args(repro)

    static = sub.add_parser(
        "static", help="static random reduction cases of Xu et al. (PCM) (Tables 5-6 style)"
    )
    static.add_argument("--draws", type=int, default=1000, help="random mixtures per case (default 1000)")
    static.add_argument("--seed", type=int, default=0, help="PRNG seed, 0 <= seed < 2**63 (default 0)")
    static.add_argument("--out", type=Path, default=Path("gmjax_out"), help="folder for the PNG and JSON")
    static.add_argument("--no-plot", action="store_true", help="skip the PNG")
    static.add_argument("--float32", action="store_true", help="run in float32 (default float64)")

    bench = sub.add_parser("bench", help="run benchmarks/bench_NAME.py (pass its options after NAME)")
    bench.add_argument("name", nargs="?", help="benchmark name; omit to list them")
    bench.add_argument("rest", nargs=argparse.REMAINDER, help="options for the benchmark, e.g. --quick")
    return parser


def _add_study_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=int, default=100, help="Monte Carlo runs (default 100)")
    p.add_argument("--filters", nargs="+", default=None, help="subset of the study's filters")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed, 0 <= seed < 2**63 (default 0)")
    p.add_argument("--chunk-size", type=int, default=None, help="runs per compiled batch (bounds memory)")
    p.add_argument("--out", type=Path, default=Path("gmjax_out"), help="folder for the JSON and PNG")
    p.add_argument("--json", action="store_true", help="print the results as JSON instead of a table")
    p.add_argument("--no-plot", action="store_true", help="skip the PNG")
    p.add_argument("--float32", action="store_true", help="run in float32 (default float64)")


class UsageError(ValueError):
    """A bad command-line value: reported in one line with exit code 2."""


def _check_common(args: argparse.Namespace) -> None:
    if not 0 <= args.seed < 2**63:
        raise UsageError(f"--seed: must satisfy 0 <= seed < 2**63, got {args.seed}")
    out = args.out
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out: {str(out)!r} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"--out: cannot create folder {str(out)!r} ({e.strerror or e})") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise UsageError(f"--out: folder {str(out)!r} is not writable")


def _set_dtype(args: argparse.Namespace) -> None:
    import jax

    jax.config.update("jax_enable_x64", not args.float32)


def _run_study(name: str, args: argparse.Namespace) -> int:
    from gmjax import studies

    if args.runs < 1:
        raise UsageError(f"--runs: must be >= 1, got {args.runs}")
    if args.chunk_size is not None and args.chunk_size < 1:
        raise UsageError(f"--chunk-size: must be >= 1, got {args.chunk_size}")
    _check_common(args)
    _set_dtype(args)
    return studies.study_main(
        name,
        args.runs,
        seed=args.seed,
        filters=args.filters,
        out=args.out,
        as_json=args.json,
        chunk_size=args.chunk_size,
        plot=not args.no_plot,
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command; user errors print one line on stderr and return 2."""
    try:
        return _main(argv)
    except (UsageError, ValueError, OSError) as e:
        msg = " ".join(str(e).split()) or type(e).__name__
        print(f"gmjax: {msg}", file=sys.stderr)
        return 2


def _main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _build_parser()
    if not argv or (argv[0].startswith("-") and argv[0] not in ("-h", "--help", "--version")):
        argv = ["study", "jump", *argv]
    args = parser.parse_args(argv)
    if args.command == "bench":
        if not args.name:
            print("available benchmarks: " + ", ".join(_available_benchmarks()))
            return 0
        return _run_bench(args.name, args.rest)
    if args.command == "static":
        from gmjax import _default_study

        if args.draws < 1:
            raise UsageError(f"--draws: must be >= 1, got {args.draws}")
        _check_common(args)
        _set_dtype(args)
        return _default_study.run(draws=args.draws, seed=args.seed, out=args.out, plot=not args.no_plot)
    from gmjax import studies

    if args.command == "reproduce":
        tables = {studies.STUDIES[n]().table: n for n in studies.STUDIES}
        if not args.table:
            print("tables gmjax reproduces (gmjax reproduce TABLE):")
            for table, n in sorted(tables.items()):
                print(f"  {table:20s} {studies.STUDIES[n]().title}")
            print("benchmarks with paper tables (gmjax bench NAME): " + ", ".join(_available_benchmarks()))
            return 0
        if args.table not in tables:
            raise UsageError(f"unknown table {args.table!r}; available: {sorted(tables)}")
        return _run_study(tables[args.table], args)
    if args.name == "list":
        for n in sorted(studies.STUDIES):
            print(f"{n:12s} {studies.STUDIES[n]().title}")
        return 0
    return _run_study(args.name, args)


if __name__ == "__main__":
    sys.exit(main())
