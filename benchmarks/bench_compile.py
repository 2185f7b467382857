"""Compile time of the main job's Table 7 programs (seed 000's jump system, 10 runs per chunk).

For each filter: its Monte Carlo study program as ``gmjax.monte_carlo`` compiles it (filter and scores
of one chunk) and the filter alone (``jit(vmap(run))`` over the chunk's measurements); once: the
simulation program every filter of the study shares. Each is traced, lowered and XLA-compiled apart
(``jax.stages``), with the number of kernels XLA:CPU compiled (``FusionCompiler::Compile`` events of a
``jax.profiler`` trace of the compile), repeated ``--repeats`` times in this one process (jit caches
are cleared: each repeat traces, lowers and compiles anew). Compile time is what issue 17 asks to bound
(≤ 3 s per Table 7 filter, or the reason).

Usage: python benchmarks/bench_compile.py [--repeats 2] [--filters NL-GSF PF] [--note "..."] [--quick]
       [--merge-with results/compile.json] (keep the rows of the programs not run now)
       (--quick: one repeat, NL-GSF and the EKF, results compile_quick.*)
"""

from __future__ import annotations

import argparse
import glob
import gzip
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

CHUNK = 10


def _timed_compile(jitted, args: tuple) -> dict:
    """Trace, lower and compile ``jitted`` at ``args``; seconds of each and the kernels compiled.

    JAX's in-process caches are cleared first, or a repeat would find the trace, the lowering and the
    executable cached (0 s)."""
    import jax

    jax.clear_caches()
    t0 = time.perf_counter()
    traced = jitted.trace(*args)
    t1 = time.perf_counter()
    lowered = traced.lower()
    t2 = time.perf_counter()
    trace_dir = tempfile.mkdtemp(prefix="gmjax_compile_")
    try:
        jax.profiler.start_trace(trace_dir)
        t3 = time.perf_counter()
        lowered.compile()
        t4 = time.perf_counter()
        jax.profiler.stop_trace()
        files = sorted(glob.glob(f"{trace_dir}/**/*.trace.json.gz", recursive=True))
        events = json.load(gzip.open(files[-1]))["traceEvents"] if files else []
    finally:
        shutil.rmtree(trace_dir, ignore_errors=True)
    kernels = sum(1 for e in events if e.get("name") == "FusionCompiler::Compile")
    return {"trace_s": t1 - t0, "lower_s": t2 - t1, "xla_s": t4 - t3, "total_s": t4 - t0, "kernels": kernels}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--filters", nargs="+", default=None, help="Table 7 filters (and EKF); default all")
    parser.add_argument("--note", default="", help="a note recorded with the results (e.g. machine load)")
    parser.add_argument("--quick", action="store_true", help="smoke run: NL-GSF and EKF, one repeat")
    parser.add_argument(
        "--merge-with",
        default=None,
        help="a previous results JSON: its rows of the programs not run now are kept (to rerun some filters)",
    )
    args = parser.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np
    from _common import markdown_table, write_results

    from gmjax import montecarlo as mc
    from gmjax import studies
    from gmjax.filters import build_ekf, run

    study = studies._seed000_table7()
    scenario = study.scenario()
    builders = dict(study.filters)
    builders["EKF"] = lambda sc: build_ekf(sc.model)
    names = args.filters or (["NL-GSF", "EKF"] if args.quick else list(builders))
    unknown = [n for n in names if n not in builders]
    if unknown:
        raise SystemExit(f"--filters: unknown {unknown}; choose from {list(builders)}")
    repeats = 1 if args.quick else args.repeats

    with open("/proc/loadavg") as f:
        load_before = f.read().split()[:3]
    mesh = jax.sharding.Mesh(np.asarray(jax.devices()), ("runs",))
    _timed_compile(jax.jit(lambda x: x * 2 + 1), (np.ones(3),))  # warm LLVM and the profiler
    simulation = mc.driver._simulation_program(scenario, CHUNK, mesh)
    key = jax.random.key(0)
    sims = simulation.jitted(key, np.uint32(0))
    start = np.uint32(0)
    results: dict[str, dict] = {"simulation": {"study": []}}
    for _ in range(repeats):
        results["simulation"]["study"].append(_timed_compile(simulation.jitted, (key, start)))
    for name in names:
        filt = builders[name](scenario)
        program, _ = mc.driver._chunk_program(filt, scenario, None, CHUNK, False, False, mesh)
        alone = jax.jit(jax.vmap(lambda z, inputs, k, f=filt: run(f, z, inputs, key=k)[1]))
        results[name] = {"study": [], "alone": []}
        for _ in range(repeats):
            results[name]["study"].append(_timed_compile(program.jitted, (sims, np.ones(CHUNK, bool))))
            results[name]["alone"].append(_timed_compile(alone, (sims.zs, sims.inputs, sims.filter_key)))
        print(name, {k: [round(r["total_s"], 2) for r in v] for k, v in results[name].items()}, flush=True)

    kept_note = ""
    if args.merge_with:
        import json

        with open(args.merge_with) as f:
            previous = json.load(f)
        kept = {k: v for k, v in previous["results"].items() if k not in results}
        results = {**{k: results[k] for k in ("simulation",)}, **kept, **{k: results[k] for k in names}}
        kept_note = (
            f" Rows of {', '.join(kept)} kept from an earlier run (load before "
            f"{' '.join(previous['loadavg_before'])}; {previous.get('note', '')})."
        )

    def span(rows: list[dict], field: str) -> str:
        lo, hi = min(r[field] for r in rows), max(r[field] for r in rows)
        return f"{lo:.2f}" if f"{lo:.2f}" == f"{hi:.2f}" else f"{lo:.2f}–{hi:.2f}"

    table = []
    for name, res in results.items():
        study_rows, alone_rows = res["study"], res.get("alone")
        table.append(
            [
                name,
                span(study_rows, "total_s"),
                span(study_rows, "xla_s"),
                study_rows[0]["kernels"],
                span(alone_rows, "total_s") if alone_rows else "",
                alone_rows[0]["kernels"] if alone_rows else "",
            ]
        )
    header = ["program", "study program s", "of which XLA s", "kernels", "filter alone s", "kernels"]
    md = "\n".join(
        [
            "# Compile time of the Table 7 programs",
            "",
            f"Seed 000's jump system, {CHUNK} runs per chunk (the main job's chunk), float64, "
            f"{repeats} repeat(s) in one process; trace + lower + XLA, kernels = XLA:CPU kernels compiled. "
            "'simulation' is compiled once per scenario and shared by every filter's study; "
            "'filter alone' is jit(vmap(run)) over the chunk's measurements.",
            f"Load average before: {' '.join(load_before)}. {args.note}{kept_note}",
            "",
            markdown_table(header, table),
        ]
    )
    path = write_results(
        "compile",
        {
            "chunk": CHUNK,
            "repeats": repeats,
            "loadavg_before": load_before,
            "note": args.note + kept_note,
            "results": results,
        },
        md,
        quick=args.quick,
    )
    print(md)
    print(f"wrote {path}")
    return results


if __name__ == "__main__":
    main()
