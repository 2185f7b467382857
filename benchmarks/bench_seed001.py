"""Seed 001 Tables 2 and 3: AGSSCKF against UKF, SCKF, GSUKF, GSCKF and a regularised PF.

Table 2: the 1-D system with Gamma process noise (eqs 44–47), 60 steps, scored on ``k <= 30`` (the
paper's table) and on the whole run. Table 3: bearings-only tracking with two sensors (eqs 48–52),
500 steps. 100 Monte Carlo runs each by default, all filters on the same simulated runs. Writes
``benchmarks/results/seed001.{json,md}`` and the Fig. 1 / Fig. 3-style RMSE and NEES curves
``seed001_gamma.png``, ``seed001_bearings.png``.

Timing: each filter's Monte Carlo is one compiled program that maps a single-run kernel over the
runs (``lax.map``), so "ms / step" is the cost of one time step of one run, as in the paper, with
compilation reported apart. The paper reports time per step; we also give each filter's time
relative to the PF (the paper's PF : AGSSCKF ratio is 96.64 / 11.62 = 8.3 in Table 2). The plain
NumPy AGSSCKF of ``benchmarks/reference/agsf_np.py`` is timed in the same process.

Usage: python benchmarks/bench_seed001.py [--quick] [--runs N] [--tables gamma bearings]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import RESULTS_DIR, markdown_table, write_results  # noqa: E402
from reference import agsf_np  # noqa: E402

from gmjax import studies  # noqa: E402
from gmjax.models import simulate  # noqa: E402
from gmjax.montecarlo import score_run, summarize  # noqa: E402
from gmjax.scenarios.bearings_only import BEARINGS_SENSORS, bearings_only  # noqa: E402
from gmjax.scenarios.gamma_system import GAMMA_PRIOR, GAMMA_PROCESS_NOISE, gamma_system  # noqa: E402

# the filters of `gmjax study gamma` / `gmjax study bearings` (UKF, SCKF, GSUKF, GSCKF, AGSSCKF, PF)
FACTORIES = studies.STUDIES["gamma"]().filters
FILTERS = list(FACTORIES)

# Tables 2 and 3 of seed 001 (ARMSE, ANEES, time per step in ms, MATLAB).
PAPER = {
    "gamma": {
        "UKF": (33.25, 433.34, 0.85),
        "SCKF": (30.12, 390.52, 0.78),
        "GSUKF": (23.22, 20.22, 8.96),
        "GSCKF": (18.86, 15.38, 8.93),
        "AGSSCKF": (18.05, 13.56, 11.62),
        "PF": (16.32, 10.67, 96.64),
    },
    "bearings": {
        "UKF": (0.1532, 246.47, 0.92),
        "SCKF": (0.1530, 215.35, 0.83),
        "GSUKF": (0.1203, 18.33, 9.92),
        "GSCKF": (0.1056, 8.91, 11.23),
        "AGSSCKF": (0.9234, 6.96, 13.22),
        "PF": (0.8021, 4.82, 120.64),
    },
}


def build(name, scenario):
    """Filter ``name`` for ``scenario``, built exactly as ``gmjax.studies`` builds it."""
    return FACTORIES[name](scenario)


def monte_carlo_mapped(filt, scenario, keys):
    """Score the runs of ``keys`` with one compiled program mapping the single-run kernel (lax.map)."""
    n_runs = keys.shape[0]
    fn = jax.jit(lambda ks: jax.lax.map(lambda k: score_run(filt, scenario, k), ks))
    t0 = time.perf_counter()
    compiled = fn.lower(keys).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    scores = jax.block_until_ready(compiled(keys))
    run_s = time.perf_counter() - t0
    scores = jax.tree_util.tree_map(np.asarray, scores)
    return summarize(scores, n_runs=n_runs, compile_s=compile_s, run_s=run_s)


def numpy_reference_time(table, scenario, n_steps):
    """Seconds per step of the NumPy AGSSCKF on one simulated run of ``n_steps`` steps."""
    _, zs, ts = simulate(scenario, jax.random.key(123))
    zs, ts = np.asarray(zs)[:n_steps], np.asarray(ts)[:n_steps]
    if table == "gamma":
        f = lambda x, t: 0.5 * x + np.sin(0.04 * np.pi * (t - 1))  # noqa: E731
        h = lambda x, t: 0.2 * x**2 if t <= 30 else 0.5 * x - 2.0  # noqa: E731
        q = (
            np.array(GAMMA_PROCESS_NOISE[0]),
            np.array(GAMMA_PROCESS_NOISE[1])[:, None],
            np.array(GAMMA_PROCESS_NOISE[2])[:, None, None],
        )
        r = (np.ones(1), np.zeros((1, 1)), np.full((1, 1, 1), 1e-5))
        prior = (
            np.array(GAMMA_PRIOR[0]),
            np.array(GAMMA_PRIOR[1])[:, None],
            np.array(GAMMA_PRIOR[2])[:, None, None],
        )
    else:
        m = scenario.model
        A = np.asarray(jax.jacfwd(m.f)(jnp.zeros(4), 1))
        S = np.asarray(BEARINGS_SENSORS)
        f = lambda x, t: A @ x  # noqa: E731
        h = lambda x, t: np.arctan2(x[1] - S[:, 1], x[0] - S[:, 0])  # noqa: E731
        q = tuple(
            np.asarray(a) for a in (m.process_noise.weights, m.process_noise.means, m.process_noise.covs)
        )
        r = tuple(
            np.asarray(a)
            for a in (m.measurement_noise.weights, m.measurement_noise.means, m.measurement_noise.covs)
        )
        prior = tuple(np.asarray(a) for a in (m.prior.weights, m.prior.means, m.prior.covs))
    filt = agsf_np.AGSSCKF(f, h, q, r)
    t0 = time.perf_counter()
    agsf_np.run(filt, prior, zs, ts)
    return (time.perf_counter() - t0) / n_steps


def run_table(table, n_runs, n_steps, key, with_window, pf_runs):
    scenario = gamma_system(n_steps=n_steps) if table == "gamma" else bearings_only(n_steps=n_steps)
    keys = jax.random.split(key, n_runs)
    results = {}
    for name in FILTERS:
        ks = keys[:pf_runs] if name == "PF" else keys
        res = monte_carlo_mapped(build(name, scenario), scenario, ks)
        results[name] = res
        print(
            f"  {name:8s} ARMSE {res.position_armse:.4g}  ANEES {res.anees:.4g}  "
            f"{1e3 * res.run_s / (res.n_runs * n_steps):.3f} ms/step  compile {res.compile_s:.1f} s",
            flush=True,
        )
    window = {}
    if with_window:  # the paper's Table 2 window k <= 30 (timed on a 30-step scenario)
        sc30 = gamma_system(n_steps=30)
        for name in FILTERS:
            res30 = monte_carlo_mapped(build(name, sc30), sc30, keys[:pf_runs] if name == "PF" else keys)
            window[name] = 1e3 * res30.run_s / (res30.n_runs * 30)
    return scenario, results, window


def _plot(table, results, path, n_steps):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover
        return None
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    k = np.arange(1, n_steps + 1)
    colors = dict(zip(FILTERS, ["0.6", "0.3", "tab:blue", "tab:orange", "tab:red", "tab:green"]))
    for name, res in results.items():
        axes[0].plot(k, res.position_rmse, label=name, lw=1, color=colors[name])
        if name not in ("UKF", "SCKF"):  # as in Figs 1 and 3: the local filters' NEES is left out
            axes[1].plot(k, res.nees, label=name, lw=1, color=colors[name])
    axes[0].set(xlabel="k", ylabel="RMSE", yscale="log", title=f"{table}: RMSE")
    axes[1].set(xlabel="k", ylabel="NEES", yscale="log", title=f"{table}: NEES")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)
    return path


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="smoke run: 3 runs, 100 bearings steps")
    parser.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default 100)")
    parser.add_argument(
        "--pf-runs-bearings",
        type=int,
        default=None,
        help="PF runs for Table 3 (the first of the same runs; default 20, CPU-bound)",
    )
    parser.add_argument("--tables", nargs="+", default=["gamma", "bearings"], choices=["gamma", "bearings"])
    args = parser.parse_args(argv)
    n_runs = args.runs or (3 if args.quick else 100)
    key = jax.random.key(2014)
    md = [
        "# Seed 001 Tables 2 and 3: AGSSCKF and its peers",
        "",
        f"{n_runs} Monte Carlo runs per table (paper: 100), every filter on the same runs. ARMSE: time "
        "average of the position RMSE (eq 42) ± its Monte Carlo standard error; ANEES: time average of "
        "the mean full-state NEES (eq 43). ms / step: one time step of one run, compiled (`lax.map` over "
        "runs), compilation apart; the paper's times are MATLAB ms per step. **Timings were taken on a "
        "shared, loaded 2-core CPU machine** (other jobs running); ratios between filters are more "
        "meaningful than absolute values. `vs PF` = time / PF time (paper: the same ratio from its table).",
        "",
        "Filters: UKF (kappa = 3 - n), SCKF, GSUKF / GSCKF = the AGSSCKF engine without splitting "
        "(psi_th = inf; UKF / SCKF sub-filters; same pruning and merging), AGSSCKF (N_max = 15, "
        "psi_th = 0.02, r = 1.5, l = 0.5, omega = 0.5), regularised SIR PF with 1000 particles "
        "(resampling every step, the filters' GM process noise).",
        "",
    ]
    data = {"n_runs": n_runs, "tables": {}}
    for table in args.tables:
        n_steps = 60 if table == "gamma" else (100 if args.quick else 500)
        print(f"{table}: {n_runs} runs x {n_steps} steps", flush=True)
        pf_runs = n_runs if table == "gamma" else min(n_runs, args.pf_runs_bearings or 20)
        scenario, results, window = run_table(table, n_runs, n_steps, key, table == "gamma", pf_runs)
        t_pf_step = results["PF"].run_s / (results["PF"].n_runs * n_steps)
        np_step = numpy_reference_time(table, scenario, min(n_steps, 60 if table == "gamma" else 50))
        rows, tjson = [], {}
        stride = 1 if n_steps <= 100 else 5
        for name, res in results.items():
            ms = 1e3 * res.run_s / (res.n_runs * n_steps)
            p = PAPER[table][name]
            entry = {
                "armse": res.position_armse,
                "armse_stderr": res.position_armse_stderr,
                "anees": res.anees,
                "ms_per_step": ms,
                "vs_pf": ms / (1e3 * t_pf_step),
                "n_runs": res.n_runs,
                "compile_s": res.compile_s,
                "mean_components": float(np.mean(res.n_components)),
                "flag_rate": res.flag_rate,
                "paper": {
                    "armse": p[0],
                    "anees": p[1],
                    "ms_per_step": p[2],
                    "vs_pf": p[2] / PAPER[table]["PF"][2],
                },
                # curves for a plot, every `curve_stride`-th step (keeps the JSON small)
                "rmse_curve": [float(f"{v:.4g}") for v in res.position_rmse[::stride]],
                "nees_curve": [float(f"{v:.4g}") for v in res.nees[::stride]],
            }
            row = [name]
            if table == "gamma":
                armse30 = float(np.mean(res.position_rmse[:30]))
                anees30 = float(np.mean(res.nees[:30]))
                entry.update({"armse_k30": armse30, "anees_k30": anees30, "ms_per_step_k30": window[name]})
                row += [
                    f"{armse30:.4g}",
                    p[0],
                    f"{anees30:.4g}",
                    p[1],
                    f"{window[name]:.3f}",
                    p[2],
                    f"{window[name] / window['PF']:.3f}",
                    f"{p[2] / PAPER[table]['PF'][2]:.3f}",
                ]
            row += [
                f"{res.position_armse:.4g} ± {res.position_armse_stderr:.2g}",
                f"{res.anees:.4g}",
                f"{ms:.3f}",
                f"{ms / (1e3 * t_pf_step):.3f}",
            ]
            if table == "bearings":
                row += [p[0], p[1], p[2], f"{p[2] / PAPER[table]['PF'][2]:.3f}"]
            row += [f"{np.mean(res.n_components):.2f}", f"{res.compile_s:.1f}"]
            rows.append(row)
            tjson[name] = entry
        ag_ms = tjson["AGSSCKF"]["ms_per_step"]
        if table == "gamma":
            header = [
                "filter",
                "ARMSE k≤30",
                "paper",
                "ANEES k≤30",
                "paper",
                "ms/step k≤30",
                "paper ms",
                "vs PF k≤30",
                "paper vs PF",
                "ARMSE all 60",
                "ANEES all 60",
                "ms/step all",
                "vs PF all",
                "components",
                "compile s",
            ]
            title = "## Table 2: 1-D system with Gamma process noise (eqs 44–47)"
            note = (
                "The paper's Table 2 covers k ≤ 30 (quadratic measurement); after k = 30 the measurement "
                "is linear (DON = 0, no splitting). The truth uses Ga(3, 2) as shape 3, scale 2 (mean 6) "
                "while eq 47 has mean 4.25 (see `gmjax.scenarios.gamma_system.gamma_system`); our ARMSE scale is "
                "far below the paper's (whose RMSE of 16–33 for a state of size ~10 we cannot reproduce "
                "from the printed model). The PF's NEES is astronomically large: with a measurement noise "
                "variance of 1e-5 its particle cloud collapses after resampling (sample impoverishment), so "
                "its covariance is far too small; GSCKF/AGSSCKF are overconfident for k <= 30 (the 2n "
                "cubature points under-represent the spread of 0.2 x^2), while GSUKF's kappa = 2 points "
                "match the Gaussian fourth moment in 1-D."
            )
        else:
            header = [
                "filter",
                "ARMSE ± s.e.",
                "ANEES",
                "ms/step",
                "vs PF",
                "paper ARMSE",
                "paper ANEES",
                "paper ms",
                "paper vs PF",
                "components",
                "compile s",
            ]
            title = "## Table 3: bearings-only tracking with two sensors (eqs 48–52)"
            note = (
                "The paper's AGSSCKF and PF ARMSE (0.9234, 0.8021) are ten times its other entries and "
                "are probably misprints of 0.09234 and 0.08021. Choices the paper leaves open (dt = 0.01, "
                "the truth = Särkkä's curved bot_demo trajectory, eq 50 read as a mixture over the white "
                "acceleration) are documented in `gmjax.scenarios.bearings_only.bearings_only`. Here the DON of "
                "every component stays below 0.2 psi_th = 0.004 after the first steps, so Step 6's rule 3 "
                "merges all components into one at every step and the Gaussian sum filters reduce to their "
                "local filter with moment-matched process noise (GSUKF and UKF, GSCKF and SCKF agree to the digits shown); AGSSCKF's "
                "few early splits change little."
            )
        stem = f"seed001_{table}" + ("_quick" if args.quick else "")
        png = _plot(table, results, RESULTS_DIR / f"{stem}.png", n_steps)
        if pf_runs < n_runs:
            slow = tjson["PF"]["ms_per_step"] / tjson["AGSSCKF"]["ms_per_step"]
            note += (
                f" The PF ({slow:.0f}x slower per step than AGSSCKF here) ran on the first {pf_runs} of the {n_runs} runs "
                "to keep the benchmark within minutes on a 2-core machine; its ARMSE has a larger error bar."
            )
        md += [
            title,
            "",
            markdown_table(header, rows),
            "",
            note,
            "",
            f"NumPy reference AGSSCKF (`benchmarks/reference/agsf_np.py`, one run, same process): "
            f"{1e3 * np_step:.2f} ms/step, {np_step * 1e3 / ag_ms:.1f}x the compiled AGSSCKF.",
            "",
        ]
        if png:
            md += [f"![{table}]({png.name})", ""]
        tjson["numpy_reference_ms_per_step"] = 1e3 * np_step
        tjson["numpy_over_jax"] = np_step * 1e3 / ag_ms
        data["tables"][table] = {"n_steps": n_steps, "curve_stride": stride, "filters": tjson}
    path = write_results("seed001", data, "\n".join(md), quick=args.quick)
    print(f"wrote {path}")
    return data


if __name__ == "__main__":
    main()
