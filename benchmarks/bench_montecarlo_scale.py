"""Bounded-memory Monte Carlo: an NL-GSF study of seed 000's jump system at N = 10^4, 10^5, 10^6 runs.

Each size runs in a fresh Python process (so its peak resident memory, ``ru_maxrss``, is its own) through
``gmjax.monte_carlo`` with streamed accumulators and the default chunking (chunks of at most 1024 runs).
Recorded per size: compile and run seconds, runs/s, peak RSS, ARMSE ± s.e., and the peak RSS relative to
the smallest size: with streaming it must not grow with N (keeping every run's seven per-step scores,
as gmjax 0.1 did, costs about 5.4 kB per run of 120 steps: 5.4 GB at 10^6 runs).

Usage: python benchmarks/bench_montecarlo_scale.py [--sizes 10000 100000 1000000] [--chunk-size C]
       [--note "machine loaded by ..."] [--checkpoint-dir DIR] [--quick]
       (--quick: sizes 1000 10000, results *_quick.*; --checkpoint-dir: each size resumes from
       DIR/scale_N.npz, so a 10^6 run can be stopped and continued later)
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

N_U = 20


def one(n: int, chunk_size: int | None, checkpoint: str | None = None) -> dict:
    """Run one study of ``n`` runs in this process and report its numbers and peak RSS.

    With ``checkpoint`` (a path) the study resumes from it and updates it after every chunk, so a long
    size can be stopped and continued; ``runs_per_s`` counts the runs done by this process only.
    """
    import jax

    jax.config.update("jax_enable_x64", True)
    from gmjax.filters.gsf import build_gsf
    from gmjax.montecarlo import monte_carlo
    from gmjax.reduction import PruneTop
    from gmjax.scenarios.jump_system import jump_system

    sc = jump_system()
    filt = build_gsf(sc.model, "ekf", PruneTop(num_out=N_U), capacity=N_U, track_ise=False)
    t0 = time.perf_counter()
    r = monte_carlo(
        filt, sc, n, jax.random.key(0), chunk_size=chunk_size, progress=False, checkpoint=checkpoint
    )
    wall = time.perf_counter() - t0
    return {
        "n_runs": n,
        "chunk_size": r.config["chunk_size"],
        "compile_s": r.compile_s,
        "run_s": r.run_s,
        "wall_s": wall,
        "runs_per_s": (n - r.resumed_runs) / r.run_s if r.run_s > 0 else float("nan"),
        "resumed_runs": r.resumed_runs,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "armse": r.armse,
        "armse_stderr": r.armse_stderr,
        "median_nees": r.median_nees,
        "n_runs_flagged": r.n_runs_flagged,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="run counts (default 1e4 1e5 1e6)")
    parser.add_argument("--chunk-size", type=int, default=None)
    parser.add_argument("--note", default="", help="a note recorded with the results (e.g. machine load)")
    parser.add_argument("--quick", action="store_true", help="smoke run: sizes 1000 10000")
    parser.add_argument(
        "--checkpoint-dir", default=None, help="resume each size from (and update) DIR/scale_N.npz"
    )
    parser.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one is not None:
        ckpt = (
            None if args.checkpoint_dir is None else str(Path(args.checkpoint_dir) / f"scale_{args.one}.npz")
        )
        print(json.dumps(one(args.one, args.chunk_size, ckpt)))
        return {}
    from _common import markdown_table, write_results

    sizes = args.sizes or ([1000, 10000] if args.quick else [10_000, 100_000, 1_000_000])
    rows, data = (
        [],
        {
            "scenario": "seed000 jump system, 120 steps",
            "filter": f"NL-GSF (EKF, PruneTop {N_U})",
            "note": args.note,
            "sizes": [],
        },
    )
    with open("/proc/loadavg") as f:
        data["loadavg_before"] = f.read().split()[:3]
    for n in sizes:
        cmd = [sys.executable, __file__, "--one", str(n)]
        if args.chunk_size:
            cmd += ["--chunk-size", str(args.chunk_size)]
        if args.checkpoint_dir:
            cmd += ["--checkpoint-dir", args.checkpoint_dir]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            raise SystemExit(f"N={n} failed:\n{res.stderr[-3000:]}")
        d = json.loads(res.stdout.strip().splitlines()[-1])
        data["sizes"].append(d)
        print(
            f"N={n}: chunk {d['chunk_size']}, compile {d['compile_s']:.1f} s, run {d['run_s']:.1f} s, "
            f"{d['runs_per_s']:.0f} runs/s, peak RSS {d['peak_rss_mb']:.0f} MB, "
            f"ARMSE {d['armse']:.4f} ± {d['armse_stderr']:.4f}, resumed runs {d['resumed_runs']}",
            flush=True,
        )
        rss_ratio = d["peak_rss_mb"] / data["sizes"][0]["peak_rss_mb"]
        rows.append(
            [
                n,
                d["chunk_size"],
                d["compile_s"],
                d["run_s"],
                d["runs_per_s"],
                d["peak_rss_mb"],
                rss_ratio,
                f"{d['armse']:.4f} ± {d['armse_stderr']:.4f}",
                d["resumed_runs"],
            ]
        )
    with open("/proc/loadavg") as f:
        data["loadavg_after"] = f.read().split()[:3]
    header = [
        "runs",
        "chunk",
        "compile s",
        "run s",
        "runs / s",
        "peak RSS MB",
        "RSS / first",
        "ARMSE ± s.e.",
        "resumed runs",
    ]
    md = (
        "# Bounded-memory Monte Carlo: NL-GSF on seed 000's jump system (120 steps)\n\n"
        + markdown_table(header, rows)
        + "\n\nEach size in a fresh process (peak RSS is that process's `ru_maxrss`, JAX and the compiled"
        " kernel included). Scores stream into per-step sums, so memory does not depend on the number of"
        " runs. Load average before / after: "
        f"{' '.join(data['loadavg_before'])} / {' '.join(data['loadavg_after'])}."
        + (f"\n\nNote: {args.note}\n" if args.note else "\n")
    )
    path = write_results("montecarlo_scale", data, md, quick=args.quick)
    print(md)
    print(f"wrote {path}")
    return data


if __name__ == "__main__":
    main()
