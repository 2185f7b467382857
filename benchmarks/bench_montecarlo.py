"""Batched Monte Carlo throughput: PCM-GSF on seed 000's scalar jump system vs a NumPy per-run loop.

For N = 1, 100, 1000, 10000 runs: compile time, run time and runs/s of one compiled
``monte_carlo`` kernel, against the plain NumPy GSF (``references/gsf_np.py``) with the
NumPy PCM (``references/pcm_numpy.py``), timed in the same process on a few runs. Both use
the same configuration: EKF components, censored pruning (ρ = 0.9544, N_u = 20), clustering and CI
merging with the λ grid search over [1, 3] (11 points, no Newton steps, since the NumPy reference
has none). A second gmjax row adds the 8 Newton steps of seed 000 Table 1 step 7.

Usage: python benchmarks/bench_montecarlo.py [--quick] [--runs 1 100 1000 10000] [--newton-runs 1 100 1000]
       [--budget-s 900]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # references/

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _common import markdown_table, write_results  # noqa: E402

from gmjax.filters.gsf import build_gsf  # noqa: E402
from gmjax.models import simulate  # noqa: E402
from gmjax.montecarlo import monte_carlo  # noqa: E402
from gmjax.reduction import PCM  # noqa: E402
from gmjax.scenarios.jump_system import jump_system  # noqa: E402
from references import gsf_np, pcm_numpy  # noqa: E402

N_U = 20


def numpy_pcm_gsf_run(scenario, key) -> float:
    """One NumPy run (simulation by gmjax, filtering in NumPy); returns its RMSE."""
    xs, zs, _ = simulate(scenario, key)
    xs, zs = np.asarray(xs), np.asarray(zs)
    m = scenario.model
    live = lambda gm: tuple(np.asarray(a)[np.asarray(gm.mask)] for a in (gm.weights, gm.means, gm.covs))  # noqa: E731
    f = lambda x, t: x / 2 + 25 * x / (1 + x**2) + 8 * np.cos(1.2 * (t - 1))  # noqa: E731
    f_jac = lambda x, t: np.atleast_2d(0.5 + 25 * (1 - x**2) / (1 + x**2) ** 2)  # noqa: E731
    h = lambda x, t: x**2 / 20 if t <= 80 else 3 * x - 4  # noqa: E731
    h_jac = lambda x, t: np.atleast_2d(x / 10 if t <= 80 else 3.0)  # noqa: E731

    def reducer(mix):
        _, (w, m, P, _, _) = pcm_numpy.pcm_grid(
            *mix, rho=0.9544, max_components=N_U, lam_lo=1.0, lam_hi=3.0, grid=11
        )
        return w / w.sum(), m, P

    est, _, _ = gsf_np.run_gsf(
        live(m.prior),
        zs,
        f,
        h,
        live(m.process_noise),
        live(m.measurement_noise),
        reducer=reducer,
        f_jac=f_jac,
        h_jac=h_jac,
    )
    return float(np.sqrt(np.mean((est - xs[1:]) ** 2)))


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="small smoke run (1 and 8 runs, 20 steps)")
    parser.add_argument("--runs", type=int, nargs="+", default=None)
    parser.add_argument("--numpy-runs", type=int, default=None, help="runs timed for the NumPy reference")
    parser.add_argument(
        "--newton-runs",
        type=int,
        nargs="+",
        default=None,
        help="run counts for the grid + Newton configuration (default: --runs)",
    )
    parser.add_argument(
        "--budget-s",
        type=float,
        default=900.0,
        help="skip a run count whose predicted time exceeds this (reported as skipped)",
    )
    args = parser.parse_args(argv)
    runs = args.runs or ([1, 8] if args.quick else [1, 100, 1000, 10000])
    n_np = args.numpy_runs or (1 if args.quick else 3)
    scenario = jump_system()
    if args.quick:
        scenario = scenario._replace(n_steps=20)

    configs = {
        "gmjax PCM-GSF (grid)": PCM(max_components=N_U, capacity=N_U, newton_steps=0),
        "gmjax PCM-GSF (grid + Newton)": PCM(max_components=N_U, capacity=N_U),
    }
    key = jax.random.key(0)

    # NumPy reference, same process, per run, on the simulations of monte_carlo's first runs
    sim_keys = [jax.random.split(k)[0] for k in jax.random.split(key, n_np)]
    t0 = time.perf_counter()
    np_rmse = [numpy_pcm_gsf_run(scenario, k) for k in sim_keys]
    np_per_run = (time.perf_counter() - t0) / n_np
    print(
        f"NumPy reference: {np_per_run:.3f} s per run (timed on {n_np} runs), mean RMSE {np.mean(np_rmse):.3f}"
    )
    same = monte_carlo(
        build_gsf(scenario.model, "ekf", configs["gmjax PCM-GSF (grid)"], capacity=N_U, track_ise=False),
        scenario,
        n_np,
        key,
        keep_runs=n_np,
        progress=False,
    )
    gm_rmse = np.sqrt(same.scores.sq_error.mean(1))
    print(
        f"same {n_np} runs: per-run RMSE NumPy {np.round(np_rmse, 4)} vs gmjax (grid) {np.round(gm_rmse, 4)}"
    )

    rows, data = (
        [],
        {
            "numpy_per_run_s": np_per_run,
            "numpy_runs_timed": n_np,
            "n_steps": scenario.n_steps,
            "same_runs_rmse_numpy": np_rmse,
            "same_runs_rmse_gmjax_grid": gm_rmse.tolist(),
            "configs": {},
        },
    )
    for name, reducer in configs.items():
        filt = build_gsf(scenario.model, "ekf", reducer, capacity=N_U, track_ise=False)
        data["configs"][name] = {}
        rate = None
        for n in runs if "Newton" not in name or args.newton_runs is None else args.newton_runs:
            if rate is not None and n / rate > args.budget_s:
                print(f"{name}: skipping N={n} (predicted {n / rate:.0f} s > budget {args.budget_s:.0f} s)")
                rows.append([name, n, "skipped", "", "", "", ""])
                data["configs"][name][str(n)] = {"skipped": True, "predicted_s": n / rate}
                continue
            r = monte_carlo(filt, scenario, n, key, chunk_size=min(n, 1000), progress=False)
            rate = n / r.run_s
            speedup = np_per_run * rate
            rows.append([name, n, r.compile_s, r.run_s, rate, speedup, r.armse])
            data["configs"][name][str(n)] = {
                "compile_s": r.compile_s,
                "run_s": r.run_s,
                "runs_per_s": rate,
                "speedup_vs_numpy": speedup,
                "armse": r.armse,
            }
            print(
                f"{name}: N={n}: compile {r.compile_s:.1f} s, run {r.run_s:.2f} s, {rate:.1f} runs/s, "
                f"{speedup:.1f}x NumPy, ARMSE {r.armse:.3f}"
            )
    header = ["implementation", "runs", "compile s", "run s", "runs / s", "throughput vs NumPy", "ARMSE"]
    rows.append(
        [
            "NumPy per-run loop (reference)",
            n_np,
            0.0,
            np_per_run * n_np,
            1.0 / np_per_run,
            1.0,
            float(np.mean(np_rmse)),
        ]
    )
    md = (
        f"# Monte Carlo throughput: PCM-GSF, seed 000 scalar jump system ({scenario.n_steps} steps)\n\n"
        + markdown_table(header, rows)
        + "\n\nOne compiled kernel per configuration runs all runs (vmap over runs, lax.scan over time);"
        " compile time is reported apart. The NumPy reference filters one run at a time with the same"
        " pruning, clustering, CI merging and λ grid, timed in the same process. Timings come from the"
        " project's 2-core CPU machine, which other jobs may share; compare ratios within one run.\n"
        f"\nSame {n_np} simulated runs through both: per-run RMSE NumPy {np.round(np_rmse, 4).tolist()}, "
        f"gmjax (grid) {np.round(gm_rmse, 4).tolist()}.\n"
    )
    path = write_results("montecarlo", data, md, quick=args.quick)
    print(md)
    print(f"wrote {path}")
    return data


if __name__ == "__main__":
    main()
