"""gmjax's Gaussian sum filters against a minimal hand-written JAX kernel of the same work (issue 17).

For each case (NL-GSF, R-GSF and PCM-GSF with the grid confidence search; the 1-D jump system of seed
000 and the 4-D range-bearing system of seed 000 Table 8; float64 and float32) the same ``N`` simulated
measurement sequences are filtered by

* gmjax: ``jit(vmap(run(build_gsf(...))))`` returning the estimates and their covariances, and
* the minimal kernel of ``references/gsf_minimal.py`` (plain ``jax.numpy``: no mixture type,
  masks, flags or validation),

in the same process, alternating, and the benchmark prints compile time apart from run time, µs per
run-step, the ratio gmjax / minimal, and the largest difference of the estimates (float64: must be
below 1e-9). ``track_ise=True`` (the per-step ISE diagnostic, opt-in) is timed as a separate gmjax row
in 1-D for NL-GSF and R-GSF.

PCM-GSF is configured as in the seed 000 studies (``PCM(max_components=20, capacity=20)``: ρ = 0.9544,
α = 0.001, the 11-point λ grid on [1, 3], range scale 0.5, CI merging; clustering on the position
dimensions (0, 2) in 4-D as for Table 8) with the Newton steps off (``newton_steps=0``): "PCM-GSF
(grid)". In float64 the same process also times PCM's default 8 Newton steps, "PCM-GSF (grid +
Newton)", and prints its ratio to the grid row (issue 17: at most 1.5×); that case times the minimal
kernel, the grid and grid + Newton in alternating rounds (one call of each per round, the best of each
kept), so that the machine's drift slows all three alike.

Usage: python benchmarks/bench_gsf_kernel.py [--runs 1000] [--runs-runnalls 200] [--runs-pcm 200]
       [--repeats 5] [--quick] [--systems 1-D 4-D] [--filters prune runnalls pcm] [--timeout 900]
       [--note "..."] [--merge-with results/gsf_kernel.json] [--render]

``--merge-with`` reruns some cases and keeps the other rows of an earlier results file (each row
records its runs and repeats; the earlier note is kept); ``--render`` only rewrites the Markdown
table from ``results/gsf_kernel.json``.

Each case (system, filter, dtype) runs in a fresh process, retried once if it gives no result within
``--timeout`` seconds (a long process hung in the XLA CPU runtime; see ``_common.run_in_fresh_process``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # references/

FILTER_NAMES = {"prune": "NL-GSF", "runnalls": "R-GSF", "pcm": "PCM-GSF (grid)"}
NEWTON_NAME = "PCM-GSF (grid + Newton)"


def _log_mix(gm, capacity: int | None = None):
    """``(log_w, means, covs)`` of a GaussianMixture, padded to ``capacity`` with ``-inf`` log weights
    (the padded slots copy the first component)."""
    w = np.asarray(gm.weights, np.float64) * np.asarray(gm.mask)
    w = w / w.sum()
    m, P = np.asarray(gm.means), np.asarray(gm.covs)
    with np.errstate(divide="ignore"):
        log_w = np.where(np.asarray(gm.mask), np.log(w), -np.inf)
    if capacity is not None and capacity > len(w):
        pad = capacity - len(w)
        log_w = np.concatenate([log_w, np.full(pad, -np.inf)])
        # dead slots copy the first component (weight 0): their arithmetic stays finite (e.g. a range
        # measurement's Jacobian at the origin would be NaN, and 0 * NaN poisons the moments)
        m = np.concatenate([m, np.broadcast_to(m[0], (pad,) + m.shape[1:])])
        P = np.concatenate([P, np.broadcast_to(P[0], (pad,) + P.shape[1:])])
    dtype = gm.means.dtype
    return tuple(jnp.asarray(a, dtype) for a in (log_w, m, P))


def _scenario(system: str, dtype):
    from gmjax.scenarios.glint_range_bearing import range_bearing
    from gmjax.scenarios.jump_system import jump_system

    if system == "1-D":
        return jump_system(dtype=dtype)
    return range_bearing(duration=1.0, dtype=dtype)  # 100 steps of the 4-D Table 8 system


def case(system: str, reducer: str, dtype, n_runs: int, repeats: int, capacity: int = 20) -> list[dict]:
    """Time gmjax and the minimal kernel on one case; returns one row per gmjax variant."""
    from _common import time_alternating, time_jax

    from gmjax.filters import run
    from gmjax.filters.gsf import build_gsf
    from gmjax.models.base import simulate
    from gmjax.reduction import PCM, PruneTop, Runnalls
    from references.gsf_minimal import minimal_gsf

    sc = _scenario(system, dtype)
    pcm_dims = None if system == "1-D" else (0, 2)  # seed 000 §IV-D clusters on position only
    model = sc.model
    keys = jax.random.split(jax.random.key(0), n_runs)
    _, zs, ts = jax.jit(jax.vmap(lambda k: simulate(sc, k)))(keys)
    ts = ts[0]
    minimal = minimal_gsf(
        model.f,
        model.h,
        _log_mix(model.prior, capacity),
        _log_mix(model.process_noise),
        _log_mix(model.measurement_noise),
        capacity,
        reducer,
        dims=pcm_dims,
    )
    minimal_fn = jax.jit(jax.vmap(minimal, (0, None)))

    def pcm(newton_steps):
        return PCM(max_components=capacity, capacity=capacity, dims=pcm_dims, newton_steps=newton_steps)

    reducers = {
        "prune": [(FILTER_NAMES["prune"], PruneTop(num_out=capacity))],
        "runnalls": [(FILTER_NAMES["runnalls"], Runnalls(num_out=capacity))],
        # the Newton refinement (seed 000 Fig. 2, 8 steps: PCM's default) against the grid alone, float64
        "pcm": [(FILTER_NAMES["pcm"], pcm(0))] + ([(NEWTON_NAME, pcm(8))] if dtype == jnp.float64 else []),
    }[reducer]
    rows: list[dict] = []
    ref = time_jax(minimal_fn, zs, ts, repeats=repeats)
    ref_est = np.asarray(minimal_fn(zs, ts)[0])
    n_steps = zs.shape[1]
    # the 4-D ISE is too slow to time; PCM's ISE row is left out (PCM dominates its cost)
    ise_options = (False, True) if system == "1-D" and reducer != "pcm" else (False,)
    variants = [(name, red, t) for name, red in reducers for t in ise_options]
    fns = []
    for _, red, track_ise in variants:
        filt = build_gsf(model, "ekf", red, capacity=capacity, track_ise=track_ise)

        def gm_run(z, filt=filt):
            info = run(filt, z, ts)[1]
            return info.mean, info.cov, info.extra.get("ise")  # the ISE, when tracked, is consumed

        fns.append(jax.jit(jax.vmap(gm_run)))
    if any(name == NEWTON_NAME for name, _, _ in variants):
        # Newton / grid is the ratio: the minimal kernel, the grid and grid + Newton are
        # timed in alternating rounds, so the machine's drift slows them alike
        calls = [lambda: minimal_fn(zs, ts)] + [lambda fn=fn: fn(zs) for fn in fns]
        ref_again, *timed = time_alternating(calls, repeats=repeats)
        ref_again["compile_s"] = ref["compile_s"]  # compiled before the rounds
        ref_agains = [ref_again] * len(fns)
    else:
        timed, ref_agains = [], []
        for fn in fns:
            timed.append(time_jax(fn, zs, repeats=repeats))
            ref_agains.append(time_jax(minimal_fn, zs, ts, repeats=repeats))  # alternate: load drifts
    for (name, _, track_ise), fn, t_gm, ref_again in zip(variants, fns, timed, ref_agains):
        ref_min = min(ref["run_min_s"], ref_again["run_min_s"])
        est = np.asarray(fn(zs)[0])
        grid_row = rows[0] if name == NEWTON_NAME else None
        rows.append(
            {
                "system": system,
                "filter": name,
                "dtype": jnp.dtype(dtype).name,
                "track_ise": track_ise,
                "n_runs": n_runs,
                "repeats": repeats,
                "n_steps": n_steps,
                "gmjax_compile_s": t_gm["compile_s"],
                "minimal_compile_s": ref["compile_s"],
                "gmjax_us_per_run_step": 1e6 * t_gm["run_min_s"] / (n_runs * n_steps),
                "minimal_us_per_run_step": 1e6 * ref_min / (n_runs * n_steps),
                "ratio": t_gm["run_min_s"] / ref_min,
                # Newton moves λ off the grid, so its estimates differ from the minimal (grid) kernel's
                "max_abs_diff": float(np.max(np.abs(est - ref_est))) if grid_row is None else float("nan"),
                "ratio_to_grid": (
                    t_gm["run_min_s"] * 1e6 / (n_runs * n_steps) / grid_row["gmjax_us_per_run_step"]
                    if grid_row is not None
                    else None
                ),
            }
        )
    return rows


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1000)
    parser.add_argument(
        "--runs-runnalls", type=int, default=200, help="runs of the R-GSF cases (its greedy loop is slow)"
    )
    parser.add_argument(
        "--runs-pcm", type=int, default=200, help="runs of the PCM-GSF cases (its search is slow)"
    )
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="100 runs, 2 repeats, float64 only")
    parser.add_argument("--systems", nargs="+", default=["1-D", "4-D"])
    parser.add_argument(
        "--filters", nargs="+", default=["prune", "runnalls", "pcm"], choices=list(FILTER_NAMES)
    )
    parser.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    parser.add_argument("--note", default="")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per case (retried once)")
    parser.add_argument(
        "--merge-with",
        default=None,
        help="a previous results JSON: its rows of the cases not run now are kept (to rerun some cases)",
    )
    parser.add_argument(
        "--render", action="store_true", help="only rewrite results/gsf_kernel.md from its JSON"
    )
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    if args.one is not None:
        import json

        system, reducer, dtype_name, runs, repeats = json.loads(args.one)
        print(json.dumps(case(system, reducer, jnp.dtype(dtype_name).type, runs, repeats)))
        return {}
    from _common import RESULTS_DIR, run_in_fresh_process, write_results

    if args.render:
        import json

        path = RESULTS_DIR / "gsf_kernel.md"
        path.write_text(render_markdown(json.loads((RESULTS_DIR / "gsf_kernel.json").read_text())))
        print(f"wrote {path}")
        return {}

    n_runs, repeats = (100, 2) if args.quick else (args.runs, args.repeats)
    dtypes = [jnp.float64] if args.quick else [jnp.dtype(name).type for name in args.dtypes]
    with open("/proc/loadavg") as f:
        load_before = f.read().split()[:3]
    rows: list[dict] = []
    failed: list[str] = []
    for system in args.systems:
        for reducer in args.filters:
            for dtype in dtypes:
                cap = {"runnalls": args.runs_runnalls, "pcm": args.runs_pcm}.get(reducer, n_runs)
                runs = min(n_runs, cap)
                name = jnp.dtype(dtype).name
                got, why = run_in_fresh_process(
                    __file__, [system, reducer, name, runs, repeats], args.timeout
                )
                if got is None:
                    failed.append(f"{system} {reducer} {name}: {why}")
                    print(f"FAILED {failed[-1]}", flush=True)
                    continue
                rows += got
                for r in got:
                    print(
                        f"{system} {r['filter']} {r['dtype']} ise={r['track_ise']}: gmjax "
                        f"{r['gmjax_us_per_run_step']:.3f} µs/run-step (compile {r['gmjax_compile_s']:.1f} s), "
                        f"minimal {r['minimal_us_per_run_step']:.3f} (compile {r['minimal_compile_s']:.1f} s), "
                        f"ratio {r['ratio']:.2f}, max |Δ est| {r['max_abs_diff']:.1e}"
                        + (
                            ""
                            if r.get("ratio_to_grid") is None
                            else f", Newton / grid {r['ratio_to_grid']:.2f}"
                        ),
                        flush=True,
                    )
    with open("/proc/loadavg") as f:
        load_after = f.read().split()[:3]
    history: list[str] = []
    if args.merge_with:
        import json

        with open(args.merge_with) as f:
            rows, merge_note, history = merge_results(rows, json.load(f))
        args.note = f"{args.note} {merge_note}".strip()
    data = {
        "rows": rows,
        "failed": failed,
        "note": args.note,
        "history": history,
        "loadavg_before": load_before,
        "loadavg_after": load_after,
    }
    md = render_markdown(data)
    path = write_results("gsf_kernel", data, md, quick=args.quick)
    print(md)
    print(f"wrote {path}")
    return data


def merge_results(rows: list[dict], previous: dict) -> tuple[list[dict], str, list[str]]:
    """Rows of ``previous`` (a results dict) for the cases not in ``rows``, then ``rows``.

    Returns ``(rows, note, history)``: ``note`` says how many cases were kept and the load of their
    run; ``history`` the earlier runs' notes, newest first (``previous``'s note, then its history).
    """
    rerun = {(r["system"], r["filter"], r["dtype"]) for r in rows}
    kept = [r for r in previous["rows"] if (r["system"], r["filter"], r["dtype"]) not in rerun]
    n_kept = len({(r["system"], r["filter"], r["dtype"]) for r in kept})
    note = (
        f"Rows of {n_kept} cases kept from an earlier run (load {' '.join(previous['loadavg_before'])}"
        f" / {' '.join(previous['loadavg_after'])})."
    )
    return kept + rows, note, _notes_of(previous)


def _notes_of(data: dict) -> list[str]:
    """A results dict's own note, then its earlier runs' notes (``history``; older results kept them
    joined in one ``previous_note``)."""
    earlier = data.get("history") or ([data["previous_note"]] if data.get("previous_note") else [])
    return [data["note"], *earlier] if data.get("note") else list(earlier)


def render_markdown(data: dict) -> str:
    """The results table and its notes from a results dict (``rows``, ``failed``, ``note``, ...)."""
    from _common import markdown_table

    header = [
        "system",
        "filter",
        "dtype",
        "ISE diag.",
        "runs",
        "gmjax µs/run-step",
        "minimal µs/run-step",
        "gmjax / minimal",
        "Newton / grid",
        "gmjax compile s",
        "minimal compile s",
        "max |Δ estimate|",
    ]
    table = [
        [
            r["system"],
            r["filter"],
            r["dtype"],
            "on" if r["track_ise"] else "off",
            r["n_runs"],
            r["gmjax_us_per_run_step"],
            r["minimal_us_per_run_step"],
            r["ratio"],
            "" if r.get("ratio_to_grid") is None else f"{r['ratio_to_grid']:.2f}",
            r["gmjax_compile_s"],
            r["minimal_compile_s"],
            "n/a" if np.isnan(r["max_abs_diff"]) else f"{r['max_abs_diff']:.1e}",
        ]
        for r in data["rows"]
    ]
    md = (
        "# gmjax's GSF against a minimal hand-written JAX kernel\n\n"
        "`jit(vmap(...))` over the table's runs, the best of several repeats after compilation"
        f" ({_repeats(data['rows'])}); the minimal kernel"
        " (`references/gsf_minimal.py`) is timed before and after each gmjax row and the faster"
        " of the two is used (the float64 PCM-GSF case: the minimal kernel, the grid and grid + Newton in"
        " alternating rounds, one call of each per round). 1-D: seed 000 jump system (120 steps, 3 × 1 noise components); 4-D: seed 000"
        " Table 8 range-bearing system (100 steps, 1 × 4). Capacity 20. PCM-GSF (grid): the seed 000"
        " studies' PCM (N_u = 20; clustering on position in 4-D) with the 11-point λ grid and no Newton"
        " steps; PCM-GSF (grid + Newton): the same with its default 8 Newton steps on the relaxed EISE"
        " (float64; timed in the grid row's process, 'Newton / grid' is their ratio; its estimates differ"
        " from the grid's, so no |Δ estimate|). Load average before / after: "
        f"{' '.join(data['loadavg_before'])} / {' '.join(data['loadavg_after'])}.\n\n"
        + markdown_table(header, table)
        + "\n"
    )
    if data["failed"]:
        md += "\nCases that could not run: " + "; ".join(data["failed"]) + "\n"
    if data["note"]:
        md += f"\nNote: {data['note']}\n"
    earlier = _notes_of({**data, "note": None})
    if earlier:
        md += "\n## Earlier runs of the kept rows, newest first\n\n" + "".join(f"- {t}\n" for t in earlier)
    return md


def _repeats(rows: list[dict]) -> str:
    """The rows' repeat counts, e.g. ``"3 repeats"`` or ``"3 or 5 repeats"`` (older rows: unknown)."""
    counts = sorted({r["repeats"] for r in rows if "repeats" in r})
    unknown = any("repeats" not in r for r in rows)
    if not counts:
        return "repeats not recorded"
    text = " or ".join(str(c) for c in counts) + " repeats"
    return text + (", some rows' not recorded" if unknown else "")


if __name__ == "__main__":
    main()
