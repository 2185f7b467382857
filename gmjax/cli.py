"""The ``gmjax`` command.

``gmjax`` with no arguments runs the default study; ``gmjax bench NAME`` runs
``benchmarks/bench_NAME.py`` from a source checkout; ``gmjax --version`` prints the version.
"""

from __future__ import annotations

import argparse
import importlib.util
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
        print(f"gmjax bench: no benchmarks/ folder next to the package ({_BENCH_DIR}); "
              "benchmarks run from a source checkout (pip install -e .)", file=sys.stderr)
        return 2
    if name not in names:
        print(f"gmjax bench: unknown benchmark {name!r}; available: {', '.join(names)}", file=sys.stderr)
        return 2
    path = _BENCH_DIR / f"bench_{name}.py"
    spec = importlib.util.spec_from_file_location(f"gmjax_bench_{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(_BENCH_DIR))
    spec.loader.exec_module(module)
    module.main(list(rest))
    return 0


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gmjax",
        description="Gaussian-mixture state estimation in JAX. With no command, runs the default study.",
    )
    parser.add_argument("--version", action="version", version=f"gmjax {gmjax.__version__}")
    sub = parser.add_subparsers(dest="command")

    default = sub.add_parser("default", help="the default study (also what plain `gmjax` runs)")
    _add_default_args(default)

    bench = sub.add_parser("bench", help="run benchmarks/bench_NAME.py (pass its options after NAME)")
    bench.add_argument("name", nargs="?", help="benchmark name; omit to list them")
    bench.add_argument("rest", nargs=argparse.REMAINDER, help="options for the benchmark, e.g. --quick")
    return parser


def _add_default_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--draws", type=int, default=1000, help="random mixtures per case (default 1000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("gmjax_out"), help="folder for the PNG and JSON")
    p.add_argument("--no-plot", action="store_true", help="skip the PNG")


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _build_parser()
    if not argv or argv[0].startswith("-") and argv[0] not in ("-h", "--help", "--version"):
        argv = ["default", *argv]
    args = parser.parse_args(argv)
    if args.command == "bench":
        if not args.name:
            print("available benchmarks: " + ", ".join(_available_benchmarks()))
            return 0
        return _run_bench(args.name, args.rest)
    from gmjax import _default_study

    return _default_study.run(draws=args.draws, seed=args.seed, out=args.out, plot=not args.no_plot)


if __name__ == "__main__":
    sys.exit(main())
