"""Cost model of gmjax's Gaussian sum filters: µs per run-step against N, K and d (issue 17 item 5).

One synthetic model whose state dimension ``d`` is a parameter, so every size uses the same work per
component: ``x_t = x_{t-1} + 0.1 sin(x_{t-1}) + v`` and ``z_t = x_t + 0.05 x_t^2 + w`` elementwise
(``m = d``), with two-component process and measurement noises (``L = J = 2``: ``4K`` updated
components per step), EKF components, ``T = 20`` steps. For NL-GSF (keep the ``K`` heaviest), R-GSF
(Runnalls to ``K``) and PCM-GSF (grid search, no Newton) the benchmark times
``jit(vmap(run(filter)))`` over ``N`` simulated runs (in calls of at most 1000 runs, as
:func:`gmjax.monte_carlo` chunks them) along three axes (each from the base point
``N = 100, K = 20, d = 1``): ``N`` in 1 … 10^5, ``K`` in 5 … 200 and ``d`` in 1 … 6. It reports µs
per run-step (run time, best of a few calls; compile time apart), fits the growth exponent on each
axis (slope of log time against log size over the upper half of the axis) and writes a table and a
PNG.

Usage: python benchmarks/bench_cost_model.py [--quick] [--note "..."] [--max-seconds S]

A size whose run time, extrapolated from the two before it, exceeds ``--max-seconds`` is skipped with
the larger ones (the table says where each axis stops).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

T_STEPS = 20
CHUNK = 1000  # runs per compiled call (as monte_carlo chunks): one 10^4-run call hung in the XLA runtime
BASE = {"N": 100, "K": 20, "d": 1}
AXES = {
    "N": [1, 10, 100, 1000, 10_000, 100_000],
    "K": [5, 10, 20, 50, 100, 200],
    "d": [1, 2, 3, 4, 6],
}
QUICK_AXES = {"N": [10, 100], "K": [5, 20], "d": [1, 2]}
FILTERS = ("NL-GSF", "R-GSF", "PCM-GSF (grid)")


def model(d: int, dtype=jnp.float64):
    """The synthetic ``d``-dimensional model (prior: one Gaussian; noises: two components each)."""
    from gmjax.mixture import GaussianMixture
    from gmjax.models import StateSpaceModel

    eye = np.eye(d)
    q = GaussianMixture.create(
        [0.7, 0.3], np.stack([np.zeros(d), np.full(d, 0.5)]), np.stack([0.1 * eye, 0.5 * eye]), dtype=dtype
    )
    r = GaussianMixture.create(
        [0.8, 0.2], np.stack([np.zeros(d), np.zeros(d)]), np.stack([0.2 * eye, 2.0 * eye]), dtype=dtype
    )
    prior = GaussianMixture.create([1.0], np.zeros((1, d)), eye[None], dtype=dtype)
    return StateSpaceModel(
        f=lambda x, t: x + 0.1 * jnp.sin(x),
        h=lambda x, t: x + 0.05 * x**2,
        process_noise=q,
        measurement_noise=r,
        prior=prior,
    )


def build(name: str, m, K: int):
    from gmjax.filters.gsf import build_gsf
    from gmjax.reduction import PCM, PruneTop, Runnalls

    reducer = {
        "NL-GSF": lambda: PruneTop(num_out=K),
        "R-GSF": lambda: Runnalls(num_out=K),
        "PCM-GSF (grid)": lambda: PCM(max_components=K, capacity=K, newton_steps=0),
    }[name]()
    return build_gsf(m, "ekf", reducer, capacity=K)


def measure(name: str, N: int, K: int, d: int, repeats: int) -> dict:
    """Compile and run seconds of one configuration; µs per run-step from the best run."""
    from gmjax.filters import run
    from gmjax.models import scenario_from_model, simulate

    m = model(d)
    sc = scenario_from_model(m, n_steps=T_STEPS)
    chunk = min(N, CHUNK)
    keys = jax.random.split(jax.random.key(0), chunk)
    _, zs, ts = jax.jit(jax.vmap(lambda k: simulate(sc, k)))(keys)
    ts = jax.tree_util.tree_map(lambda a: a[0], ts)
    filt = build(name, m, K)
    fn = jax.jit(jax.vmap(lambda z: run(filt, z, ts)[1].mean))
    t0 = time.perf_counter()
    compiled = fn.lower(zs).compile()
    compile_s = time.perf_counter() - t0
    runs: list[float] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(N // chunk):  # N runs as N / chunk calls of the compiled chunk
            compiled(zs).block_until_ready()
        runs.append(time.perf_counter() - t0)
        if runs[-1] > 10.0:  # long runs: one is enough
            break
    best = min(runs)
    return {
        "filter": name,
        "N": N,
        "K": K,
        "d": d,
        "compile_s": compile_s,
        "run_s": best,
        "us_per_run_step": 1e6 * best / (N * T_STEPS),
    }


def _predicted(done: list[tuple[float, float]], size: float) -> float:
    """Run seconds at ``size`` extrapolated from the last two points (growth exponent at least 1)."""
    (s1, t1) = done[-1]
    slope = 1.0
    if len(done) > 1:
        (s0, t0) = done[-2]
        slope = max(1.0, float(np.log(t1 / t0) / np.log(s1 / s0)))
    return t1 * (size / s1) ** slope


def growth(points: list[tuple[float, float]]) -> float:
    """Slope of log(total run time) against log(size) over the upper half of an axis."""
    pts = sorted(points)[len(points) // 2 - (len(points) % 2 == 0) :]
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0]) if len(pts) > 1 else float("nan")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two sizes per axis, small N")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--max-seconds", type=float, default=30.0, help="skip the sizes whose run is predicted to take longer"
    )
    parser.add_argument(
        "--timeout", type=float, default=300.0, help="seconds per configuration (retried once)"
    )
    parser.add_argument("--filters", nargs="+", choices=FILTERS, default=list(FILTERS))
    parser.add_argument(
        "--merge-with",
        default=None,
        help="a previous results JSON: its rows of the filters not run now are kept (to rerun some filters)",
    )
    parser.add_argument("--note", default="")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    if args.one is not None:
        import json

        print(json.dumps(measure(*json.loads(args.one))))
        return {}
    from _common import markdown_table, run_in_fresh_process, write_results

    axes = QUICK_AXES if args.quick else AXES
    base = {"N": 100, "K": 5, "d": 1} if args.quick else BASE
    with open("/proc/loadavg") as f:
        load_before = f.read().split()[:3]
    rows: list[dict] = []
    hung: list[str] = []
    for name in args.filters:
        for axis, sizes in axes.items():
            for size in sizes:
                cfg = dict(base, **{axis: size})
                payload = [name, cfg["N"], cfg["K"], cfg["d"], args.repeats]
                r, why = run_in_fresh_process(__file__, payload, args.timeout)
                if why is not None and not why.startswith("no result"):
                    raise SystemExit(f"{name} N={cfg['N']} K={cfg['K']} d={cfg['d']} failed: {why}")
                if r is None:
                    hung.append(f"{name} N={cfg['N']} K={cfg['K']} d={cfg['d']}")
                    print(
                        f"{name:15s} {axis}={size}: no result within {args.timeout:.0f} s (skipped)",
                        flush=True,
                    )
                    break
                r["axis"] = axis
                rows.append(r)
                print(
                    f"{name:15s} {axis}={size:<7d} N={cfg['N']} K={cfg['K']} d={cfg['d']}: "
                    f"{r['us_per_run_step']:10.3f} µs/run-step, run {r['run_s']:.3f} s, "
                    f"compile {r['compile_s']:.1f} s",
                    flush=True,
                )
                done = [(q[axis], q["run_s"]) for q in rows if q["filter"] == name and q["axis"] == axis]
                nxt = sizes[sizes.index(size) + 1] if size != sizes[-1] else None
                if nxt is not None and _predicted(done, nxt) > args.max_seconds:
                    print(f"  (the next size would run over {args.max_seconds:.0f} s: larger {axis} skipped)")
                    break
    with open("/proc/loadavg") as f:
        load_after = f.read().split()[:3]
    if args.merge_with:
        import json

        with open(args.merge_with) as f:
            previous = json.load(f)
        kept = [r for r in previous["rows"] if r["filter"] not in args.filters]
        rows = sorted(kept + rows, key=lambda r: FILTERS.index(r["filter"]))
        hung = [h for h in previous["hung"] if not h.startswith(tuple(args.filters))] + hung
        names = sorted({r["filter"] for r in kept}, key=FILTERS.index)
        args.note += f" Rows of {', '.join(names)} from an earlier run"
        args.note += (
            f" (load {' '.join(previous['loadavg_before'])} / {' '.join(previous['loadavg_after'])})."
        )
    present = [name for name in FILTERS if any(r["filter"] == name for r in rows)]
    slopes = {
        name: {
            axis: growth([(r[axis], r["run_s"]) for r in rows if r["filter"] == name and r["axis"] == axis])
            for axis in axes
        }
        for name in present
    }
    header = ["filter", "axis", "N", "K", "d", "µs / run-step", "run s", "compile s"]
    table = [
        [r["filter"], r["axis"], r["N"], r["K"], r["d"], r["us_per_run_step"], r["run_s"], r["compile_s"]]
        for r in rows
    ]
    slope_rows = [[name] + [slopes[name][a] for a in axes] for name in present]
    md = (
        "# Cost model: µs per run-step of the GSFs against N, K and d\n\n"
        f"Synthetic model (`benchmarks/bench_cost_model.py`): EKF components, L = J = 2 noise components "
        f"(4K updated components per step), T = {T_STEPS}; each axis varied from N = {base['N']}, "
        f"K = {base['K']}, d = {base['d']}; `jit(vmap(run))`, best of {args.repeats} runs after compilation. "
        f"Load average before / after: {' '.join(load_before)} / {' '.join(load_after)}.\n\n"
        "## Growth exponents (slope of log total run time against log size, upper half of each axis)\n\n"
        + markdown_table(["filter"] + [f"in {a}" for a in axes], slope_rows)
        + "\n\n## Measurements\n\n"
        + markdown_table(header, table)
        + "\n"
    )
    if hung:
        md += "\nNo result within the timeout (skipped with the larger sizes): " + "; ".join(hung) + "\n"
    if args.note:
        md += f"\nNote: {args.note}\n"
    data = {
        "rows": rows,
        "growth": slopes,
        "hung": hung,
        "note": args.note,
        "loadavg_before": load_before,
        "loadavg_after": load_after,
    }
    path = write_results("cost_model", data, md, quick=args.quick)
    _plot(rows, axes, path.with_suffix(".png"))
    print(md)
    print(f"wrote {path}")
    return data


def _plot(rows: list[dict], axes: dict, path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no plot")
        return
    fig, panels = plt.subplots(1, len(axes), figsize=(4.2 * len(axes), 3.6))
    for ax, axis in zip(panels, axes):
        for name in FILTERS:
            pts = sorted(
                (r[axis], r["us_per_run_step"]) for r in rows if r["filter"] == name and r["axis"] == axis
            )
            if pts:
                ax.loglog(*zip(*pts), "o-", label=name)
        ax.set_xlabel({"N": "runs N", "K": "capacity K", "d": "state dimension d"}[axis])
        ax.set_ylabel("µs per run-step")
        ax.grid(True, which="both", alpha=0.3)
    panels[0].legend()
    fig.suptitle("gmjax GSF cost model (run time, compilation apart)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
