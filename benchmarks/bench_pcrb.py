"""Seed 002 §V-B: PCRB of the 1-D benchmark by GMM-quadrature (K = 64, 32) vs Monte Carlo.

Reproduces Figs 3-5 (bounds and relative errors against a 10^7-sample Monte Carlo reference, beside
a 1.2x10^4-sample Monte Carlo) and the paper's wall times (MATLAB: 1400.712 s for K = 64, 225.141 s
for K = 32, 99.7 % / 99.0 % of it in k-means; 4.157 s for the small Monte Carlo). The same
Algorithm 2 written as a plain NumPy loop (references/pcrb_ref.py) runs in the same
process for the speed ratio.

Writes benchmarks/results/pcrb.json (per-step bounds under ``ungm_time``, ``ungm_gmm_k64``,
``ungm_gmm_k32``, ``ungm_mc_reference``, ``ungm_mc_small``) and pcrb.md.

Satellite tracking (§V-C, Figs 9-10): position / velocity PCRB (sqrt of the trace of the position /
velocity block) by the 49-component GMM with the 13-point level-2 Smolyak rule, with and without
range rate, against a 10^5-sample Monte Carlo reference, beside a 1200-sample Monte Carlo (paper:
GMM 34.091 s / 33.977 s, small MC 35.039 s / 33.307 s).

    python benchmarks/bench_pcrb.py            # full: 10^7-sample reference (a few minutes)
    python benchmarks/bench_pcrb.py --quick    # 2x10^5-sample reference, K = 64 / 32, T = 100
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
from _common import RESULTS_DIR, markdown_table, time_jax, time_python, write_results  # noqa: E402

from gmjax.pcrb import build_pcrb_gmm, pcrb_mc  # noqa: E402
from gmjax.quadrature import gauss_hermite, smolyak  # noqa: E402
from gmjax.scenarios.growth_model import ungm, ungm_gmm_setup  # noqa: E402
from gmjax.scenarios.satellite_pass import satellite  # noqa: E402
from references.pcrb_ref import (  # noqa: E402
    gh_library,
    pcrb_gmm_1d_numpy,
    pcrb_mc_numpy,
    split_1d,
)

PAPER = {
    "gmm_k64_s": 1400.712,
    "gmm_k32_s": 225.141,
    "mc_small_s": 4.157,
    "max_rel_err_k64": 0.01,
    "max_rel_err_k32": 0.015,
    "sat_gmm_rae_s": 34.091,
    "sat_gmm_raer_s": 33.977,
    "sat_mc_small_rae_s": 35.039,
    "sat_mc_small_raer_s": 33.307,
}


def mc_seconds_per_sample(run_mc, n_pilot: int) -> float:
    """Wall seconds per Monte Carlo sample: a pilot of ``n_pilot`` samples, timed after its compile."""
    jax.block_until_ready(run_mc(n_pilot, 101))  # compile
    t0 = time.perf_counter()
    jax.block_until_ready(run_mc(n_pilot, 102))
    return (time.perf_counter() - t0) / n_pilot


def equal_time_plot(data: dict, path: Path) -> Path | None:
    """Relative error per step: the GMM method vs Monte Carlo with the samples that take its run time."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover
        return None
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
    for (label, (e_gmm, e_mc, n_eq)), c in zip(data["ungm"].items(), ("tab:blue", "tab:orange")):
        k = np.arange(1, len(e_gmm) + 1)
        axes[0].plot(k, e_gmm, color=c, label=label)
        axes[0].plot(k, e_mc, color=c, ls="--", label=f"MC {n_eq:.1e} (same time)")
    axes[0].set(xlabel="n", ylabel="relative error of J_n^-1", yscale="log", title="1-D benchmark (K = 64)")
    axes[0].legend(fontsize=6)
    for tag, c in (("rae", "tab:green"), ("raer", "tab:red")):
        if tag in data["sat"]:
            e_gmm, e_mc, n_eq = data["sat"][tag]
            k = np.arange(1, len(e_gmm) + 1)
            axes[1].plot(k, e_gmm, color=c, label=f"GMM-49 ({tag.upper()})")
            axes[1].plot(k, e_mc, color=c, ls="--", label=f"MC {n_eq} ({tag.upper()}, same time)")
    axes[1].set(xlabel="measurement", ylabel="relative error of PPCRB", yscale="log", title="satellite")
    axes[1].legend(fontsize=6)
    fig.suptitle("PCRB accuracy at equal wall time (reference: large Monte Carlo)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def _pos_vel(bound):
    b = np.asarray(bound)
    return (
        np.sqrt(np.trace(b[:, :3, :3], axis1=1, axis2=2)),
        np.sqrt(np.trace(b[:, 3:, 3:], axis1=1, axis2=2)),
    )


def satellite_part(args, key):
    """Figs 9-10: GMM-49 vs MC reference and small MC, with and without range rate."""
    n_ref = args.sat_mc_samples or (3_000 if args.quick else 100_000)
    out, rows = {}, []
    for rr in (False, True):
        tag = "raer" if rr else "rae"
        t0 = time.perf_counter()
        sc = satellite(range_rate=rr)
        t_build = time.perf_counter() - t0
        T = len(sc.times) - 1
        run = build_pcrb_gmm(sc.model, smolyak(6, 2), T, sc.config)
        timing = time_jax(lambda: run(sc.prior_gm).bound, repeats=1 if args.quick else 3)
        res = run(sc.prior_gm)
        pg, vg = _pos_vel(res.bound)

        def small(seed):
            return pcrb_mc(
                sc.model,
                T,
                args.sat_small_samples,
                key=jax.random.fold_in(key, seed),
                chunk_size=args.sat_small_samples,
                progress=False,
            ).bound

        t_small = time_jax(lambda: small(11), repeats=1 if args.quick else 3)
        ps, vs = _pos_vel(small(11))
        t0 = time.perf_counter()
        ref = pcrb_mc(
            sc.model, T, n_ref, key=jax.random.fold_in(key, 12), chunk_size=min(10_000, max(n_ref // 10, 1))
        )
        t_ref = time.perf_counter() - t0
        pr, vr = _pos_vel(ref.bound)
        out[f"sat_{tag}_time"] = sc.times
        out[f"sat_{tag}_gmm_ppcrb"], out[f"sat_{tag}_gmm_vpcrb"] = pg, vg
        out[f"sat_{tag}_mc_reference_ppcrb"], out[f"sat_{tag}_mc_reference_vpcrb"] = pr, vr
        out[f"sat_{tag}_mc_small_ppcrb"], out[f"sat_{tag}_mc_small_vpcrb"] = ps, vs
        out[f"sat_{tag}_metric"] = np.asarray(res.info.metric)
        for name, p, v, tm, paper in (
            ("GMM-49", pg, vg, timing, PAPER[f"sat_gmm_{tag}_s"]),
            (f"MC {args.sat_small_samples}", ps, vs, t_small, PAPER[f"sat_mc_small_{tag}_s"]),
        ):
            rows.append(
                [
                    ("R, A, E, Rdot" if rr else "R, A, E"),
                    name,
                    float(np.max(_rel(p[1:], pr[1:]))),
                    float(np.max(_rel(v[1:], vr[1:]))),
                    tm["compile_s"],
                    tm["run_median_s"],
                    paper,
                ]
            )
        rows.append(
            [("R, A, E, Rdot" if rr else "R, A, E"), f"MC reference {n_ref:.0e}", "", "", "", t_ref, ""]
        )
        rate_s = mc_seconds_per_sample(
            lambda n, seed: (
                pcrb_mc(sc.model, T, n, key=jax.random.fold_in(key, seed), chunk_size=n, progress=False).bound
            ),
            2_000 if not args.quick else 200,
        )
        n_eq = max(int(timing["run_median_s"] / rate_s), 10)

        def mc_eq(seed, n=n_eq):
            return pcrb_mc(
                sc.model, T, n, key=jax.random.fold_in(key, seed), chunk_size=n, progress=False
            ).bound

        jax.block_until_ready(mc_eq(91))  # compile for this sample count
        t0 = time.perf_counter()
        pe, ve = _pos_vel(jax.block_until_ready(mc_eq(13)))
        t_eq = time.perf_counter() - t0
        ep_g, ep_m = _rel(pg[1:], pr[1:]), _rel(pe[1:], pr[1:])
        out[f"sat_{tag}_equal_time"] = {
            "gmm_run_s": timing["run_median_s"],
            "gmm_max_rel_err_ppcrb": float(ep_g.max()),
            "gmm_max_rel_err_vpcrb": float(_rel(vg[1:], vr[1:]).max()),
            "mc_samples": n_eq,
            "mc_run_s": t_eq,
            "mc_max_rel_err_ppcrb": float(ep_m.max()),
            "mc_max_rel_err_vpcrb": float(_rel(ve[1:], vr[1:]).max()),
            "reference_samples": n_ref,
        }
        out[f"sat_{tag}_equal_time_curves"] = {"gmm_ppcrb_rel": ep_g, "mc_ppcrb_rel": ep_m}
        out[f"sat_{tag}_summary"] = {
            "steps": T,
            "arc_s": float(sc.times[-1]),
            "theta0": sc.theta0,
            "build_s": t_build,
            "min_ppcrb_at_s": float(sc.times[1 + int(np.argmin(pg[1:]))]),
            "max_metric": float(np.max(res.info.metric)),
        }
    md = [
        "## Satellite tracking (seed 002 §V-C, Figs 9-10)",
        "",
        f"Reference: Monte Carlo with {n_ref:.0e} trajectories. PPCRB / VPCRB = sqrt(trace) of the "
        "position / velocity block. Arc: every 5 s from t = 0 while the reference elevation is "
        f"positive ({out['sat_rae_summary']['steps']} measurements, "
        f"{out['sat_rae_summary']['arc_s']:.0f} s); minimum PPCRB (R, A, E) at "
        f"t = {out['sat_rae_summary']['min_ppcrb_at_s']:.0f} s (paper: about 600 s); "
        f"max nonlinearity metric {out['sat_rae_summary']['max_metric']:.3g} (threshold 0.01).",
        "",
        markdown_table(
            [
                "measurements",
                "method",
                "max rel. err. PPCRB",
                "max rel. err. VPCRB",
                "compile s",
                "run s",
                "paper run s (MATLAB)",
            ],
            rows,
        ),
        "",
        "Accuracy at equal wall time: Monte Carlo with the number of samples that takes the GMM-49 run "
        f"time (measured rate), against the {n_ref:.0e}-sample reference (whose own sampling error bounds "
        "what can be resolved):",
        "",
        markdown_table(
            [
                "measurements",
                "GMM-49 run s",
                "GMM max rel. err. PPCRB",
                "MC samples",
                "MC run s",
                "MC max rel. err. PPCRB",
                "more accurate",
            ],
            [
                [
                    "R, A, E, Rdot" if tag == "raer" else "R, A, E",
                    e["gmm_run_s"],
                    e["gmm_max_rel_err_ppcrb"],
                    e["mc_samples"],
                    e["mc_run_s"],
                    e["mc_max_rel_err_ppcrb"],
                    "MC" if e["mc_max_rel_err_ppcrb"] < e["gmm_max_rel_err_ppcrb"] else "GMM",
                ]
                for tag, e in ((t, out[f"sat_{t}_equal_time"]) for t in ("rae", "raer"))
            ],
        ),
    ]
    return out, "\n".join(md)


def _f(x, n):
    return x / 2 + 25 * x / (1 + x * x) + 8 * np.cos(1.2 * n)


def _fp(x, n):
    return 0.5 + 25 * (1 - x * x) / (1 + x * x) ** 2


def _hp(x, n):
    return x / 10


def _rel(b, ref):
    return np.abs(b - ref) / ref


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small Monte Carlo reference")
    ap.add_argument("--mc-samples", type=int, default=None, help="reference MC samples (1e7)")
    ap.add_argument("--small-samples", type=int, default=12_000, help="small MC samples")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--quad-order", type=int, default=40, help="Gauss-Hermite nodes per component")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sat-mc-samples", type=int, default=None, help="satellite reference MC (1e5)")
    ap.add_argument("--sat-small-samples", type=int, default=1200)
    ap.add_argument("--skip-satellite", action="store_true")
    args = ap.parse_args(argv)
    n_ref = args.mc_samples or (200_000 if args.quick else 10_000_000)
    T = args.steps
    model = ungm()
    rule = gauss_hermite(1, args.quad_order)
    key = jax.random.PRNGKey(args.seed)

    # --- Monte Carlo reference (chunked, progress bar on stderr) ------------------------------
    t0 = time.perf_counter()
    mc_ref = pcrb_mc(
        model, T, n_ref, key=jax.random.fold_in(key, 1), chunk_size=min(250_000, max(n_ref // 20, 1))
    )
    t_ref = time.perf_counter() - t0
    ref = np.asarray(mc_ref.bound[:, 0, 0])
    ref_se = np.asarray(mc_ref.info.bound_stderr[:, 0, 0])

    # --- small Monte Carlo (1.2e4 samples): compile apart from run -----------------------------
    def small_mc(seed):
        return pcrb_mc(
            model,
            T,
            args.small_samples,
            key=jax.random.fold_in(key, seed),
            chunk_size=args.small_samples,
            progress=False,
        ).bound

    t_small = time_jax(lambda: small_mc(2), repeats=3)
    mc_small = np.asarray(small_mc(2)[:, 0, 0])

    rng = np.random.default_rng(args.seed)
    t_small_np = time_python(
        lambda: pcrb_mc_numpy(
            lambda X, n: _f(X, n),
            lambda X, n: _fp(X, n)[..., None],
            lambda X, n: _hp(X, n)[..., None],
            np.eye(1) * 10.0,
            np.eye(1),
            np.zeros(1),
            np.eye(1),
            T,
            args.small_samples,
            rng,
        ),
        repeats=3,
    )

    # --- GMM-quadrature, the paper's configuration ---------------------------------------------
    results = {}
    rows_err = []
    rows_time = []
    for K in (64, 32):
        setup = ungm_gmm_setup(model, K, state_components=16)  # the paper's state library M = 16
        run = build_pcrb_gmm(model, rule, T, setup.config)
        timing = time_jax(lambda: run(setup.prior_gm).bound, repeats=1 if args.quick else 3)
        res = run(setup.prior_gm)
        b = np.asarray(res.bound[:, 0, 0])
        results[K] = (b, res, timing)
        # NumPy reference of the same Algorithm 2 (loops over time and k-means iterations)
        pw, pm, pv = split_1d(np.ones(1), np.zeros(1), np.ones(1), gh_library(8, 0.5))
        for _ in range(3):
            pw, pm, pv = split_1d(pw, pm, pv, gh_library(8, 0.5))
        t0 = time.perf_counter()
        b_np = pcrb_gmm_1d_numpy(
            _f,
            _fp,
            _hp,
            10.0,
            1.0,
            pw,
            pm,
            pv,
            1.0,
            T,
            K,
            gh_library(16, 1 / 40),
            gh_library(8, 0.5),
            args.quad_order,
        )
        t_np = time.perf_counter() - t0
        rel = _rel(b[1:], ref[1:])
        rel_rmse = _rel(np.sqrt(b[1:]), np.sqrt(ref[1:]))
        rows_err.append(
            [
                f"GMM K = {K}, M = 16 (paper)",
                float(rel_rmse.max()),
                PAPER[f"max_rel_err_k{K}"],
                float(rel.max()),
                int(rel.argmax()) + 1,
                float(rel.mean()),
            ]
        )
        rows_time.append(
            [
                f"GMM K = {K}, M = 16 (paper; whole run)",
                timing["compile_s"],
                timing["run_median_s"],
                t_np,
                t_np / timing["run_median_s"],
                PAPER[f"gmm_k{K}_s"],
                float(np.max(np.abs(b_np - b)[:11])),
                float(np.max(np.abs(b_np - b))),
            ]
        )
    rel_small = _rel(mc_small[1:], ref[1:])
    rows_err.append(
        [
            f"MC {args.small_samples} samples",
            float(_rel(np.sqrt(mc_small[1:]), np.sqrt(ref[1:])).max()),
            "> GMM (Fig 4)",
            float(rel_small.max()),
            int(rel_small.argmax()) + 1,
            float(rel_small.mean()),
        ]
    )
    rows_time.append(
        [
            f"MC {args.small_samples} samples",
            t_small["compile_s"],
            t_small["run_median_s"],
            t_small_np["run_median_s"],
            t_small_np["run_median_s"] / t_small["run_median_s"],
            PAPER["mc_small_s"],
            "",
            "",
        ]
    )
    rows_time.append([f"MC reference {n_ref:.0e} samples", "", t_ref, "", "", "", "", ""])

    # --- the default: K = 64 with the state library M = 32 (see ungm_gmm_setup) ----------------
    setup = ungm_gmm_setup(model, 64)
    assert len(setup.state_library.weights) == 32
    run32 = build_pcrb_gmm(model, rule, T, setup.config)
    t32 = time_jax(lambda: run32(setup.prior_gm).bound, repeats=1 if args.quick else 3)
    b32 = np.asarray(run32(setup.prior_gm).bound[:, 0, 0])
    rel32 = _rel(b32[1:], ref[1:])
    rows_err.insert(
        0,
        [
            "GMM K = 64, M = 32 (default)",
            float(_rel(np.sqrt(b32[1:]), np.sqrt(ref[1:])).max()),
            "0.01 (K = 64)",
            float(rel32.max()),
            int(rel32.argmax()) + 1,
            float(rel32.mean()),
        ],
    )
    rows_time.insert(
        0, ["GMM K = 64, M = 32 (default)", t32["compile_s"], t32["run_median_s"], "", "", "", "", ""]
    )

    # --- accuracy at equal wall time: Monte Carlo with the samples that take the GMM's run time --
    eq_rows, eq_data, eq_curves = [], {}, {}
    rate = mc_seconds_per_sample(
        lambda n, seed: (
            pcrb_mc(
                model, T, n, key=jax.random.fold_in(key, seed), chunk_size=min(n, 250_000), progress=False
            ).bound
        ),
        200_000 if not args.quick else 20_000,
    )
    for label, t_gmm, b_gmm in (
        ("GMM K = 64, M = 32 (default)", t32["run_median_s"], b32),
        ("GMM K = 64, M = 16 (paper)", results[64][2]["run_median_s"], results[64][0]),
    ):
        n_eq = max(int(t_gmm / rate), 100)

        def mc_at(seed, n=n_eq):
            return pcrb_mc(
                model, T, n, key=jax.random.fold_in(key, seed), chunk_size=min(n, 250_000), progress=False
            ).bound

        jax.block_until_ready(mc_at(90 + len(eq_rows)))  # compile for this sample count
        t0 = time.perf_counter()
        b_eq = np.asarray(jax.block_until_ready(mc_at(3 + len(eq_rows)))[:, 0, 0])
        t_eq = time.perf_counter() - t0
        e_gmm, e_mc = _rel(b_gmm[1:], ref[1:]), _rel(b_eq[1:], ref[1:])
        eq_rows.append(
            [
                label,
                t_gmm,
                float(e_gmm.max()),
                f"MC {n_eq:.2e}",
                t_eq,
                float(e_mc.max()),
                "MC" if e_mc.max() < e_gmm.max() else "GMM",
            ]
        )
        eq_data[label] = {
            "gmm_run_s": t_gmm,
            "gmm_max_rel_err": float(e_gmm.max()),
            "mc_samples": n_eq,
            "mc_run_s": t_eq,
            "mc_max_rel_err": float(e_mc.max()),
        }
        eq_curves[label] = (e_gmm, e_mc, n_eq)

    mc_rel_se = float(np.max(ref_se[1:] / ref[1:]))
    b64, res64, _ = results[64]
    data = {
        "config": {
            "steps": T,
            "mc_reference_samples": n_ref,
            "mc_small_samples": args.small_samples,
            "quad_order": args.quad_order,
            "seed": args.seed,
        },
        "ungm_time": list(range(T + 1)),
        "ungm_gmm_k64": b64,
        "ungm_gmm_k32": results[32][0],
        "ungm_mc_reference": ref,
        "ungm_mc_reference_stderr": ref_se,
        "ungm_mc_small": mc_small,
        "ungm_gmm_k64_state_m32": b32,
        "default": "K = 64 with state library M = 32 (ungm_gmm_setup's default); ungm_gmm_k64 / _k32 are M = 16",
        "equal_time_ungm": eq_data,
        "mc_seconds_per_sample_ungm": rate,
        "ungm_metric_s_case_k64": np.asarray(res64.info.metric),
        "ungm_metric_l_case_k64": np.asarray(res64.info.metric_refined),
        "errors": [
            dict(zip(["method", "max_rel_err_sqrt", "paper", "max_rel_err", "at_step", "mean_rel_err"], r))
            for r in rows_err
        ],
        "timings": [
            dict(
                zip(
                    [
                        "part",
                        "compile_s",
                        "run_s",
                        "numpy_s",
                        "numpy_over_jax",
                        "paper_matlab_s",
                        "max_abs_diff_vs_numpy_steps_0_10",
                        "max_abs_diff_vs_numpy",
                    ],
                    r,
                )
            )
            for r in rows_time
        ],
        "mc_reference_max_rel_stderr": mc_rel_se,
        "paper": PAPER,
    }
    sat_md = "Satellite tracking (§V-C): skipped (--skip-satellite)."
    plot_data = {"ungm": eq_curves, "sat": {}}
    if not args.skip_satellite:
        sat, sat_md = satellite_part(args, key)
        for tag in ("rae", "raer"):
            c = sat.pop(f"sat_{tag}_equal_time_curves")
            plot_data["sat"][tag] = (
                c["gmm_ppcrb_rel"],
                c["mc_ppcrb_rel"],
                sat[f"sat_{tag}_equal_time"]["mc_samples"],
            )
        data.update(sat)
    png = equal_time_plot(plot_data, RESULTS_DIR / f"pcrb_equal_time{'_quick' if args.quick else ''}.png")
    md = [
        "# PCRB of the 1-D benchmark (seed 002 §V-B, Figs 3-5)",
        "",
        f"Reference: Monte Carlo with {n_ref:.0e} trajectories (max relative standard error of the "
        f"bound {mc_rel_se:.2e}). Steps 1..{T}; time convention of eq 79: cos(1.2 n), n the index "
        "of x_n. Timings on a shared, loaded 2-core CPU machine (another benchmark used about one core "
        "during this run), so the absolute seconds are high; the equal-time comparison measures both methods "
        "under the same load.",
        "",
        "## Relative error against the reference",
        "",
        markdown_table(
            [
                "method",
                "max rel. error of sqrt(PCRB)",
                "paper (max)",
                "max rel. error of J_n^{-1}",
                "at step",
                "mean rel. error of J_n^{-1}",
            ],
            rows_err,
        ),
        "",
        "Default configuration: K = 64 with the state library M = 32 at σ = 1/40 "
        "(`ungm_gmm_setup`'s default), chosen because the paper judges a splitting library by its L2 "
        "distance to N(0, 1) (eq 13) and its printed M = 16 is far from it at σ = 1/40 (E = 2.19; M = 32: "
        "1.48); M = 32 is the first doubling of the paper's M, not a search. The paper-literal M = 16 rows "
        "are kept. (Checked and unchanged: 80 instead of 40 Gauss-Hermite nodes per component, and 1000 "
        "instead of 100 k-means iterations, move the K = 64, M = 16 bound by < 3e-5 relative.)",
        "",
        "Reading of Figs 4-5 (documented, not tuned): the paper plots the PCRB in RMSE units -- "
        "Fig 3 shows the 'minimum RMSE' sqrt(PCRB), and §V-C defines its PCRBs (PPCRB, VPCRB) and "
        "their relative errors on the square root of the trace -- so its 1 % / 1.5 % claims are "
        "compared with the relative error of sqrt(PCRB). The relative error of the bound J_n^{-1} "
        "itself is about twice as large and is reported beside it.",
        "",
        "## Wall time (seconds)",
        "",
        markdown_table(
            [
                "part",
                "compile",
                "run",
                "NumPy ref. run",
                "NumPy / gmjax",
                "paper (MATLAB)",
                "max abs diff NumPy, n <= 10",
                "max abs diff NumPy, all n",
            ],
            rows_time,
        ),
        "",
        "The NumPy reference runs the same Algorithm 2; k-means assignments are discontinuous, so "
        "rounding differences eventually send a component to another cluster and the two runs "
        "drift apart by about the method's own error after a few tens of steps.",
        "",
        "## Accuracy at equal wall time (1-D benchmark)",
        "",
        "Monte Carlo PCRB (`gmjax.pcrb.pcrb_mc`, batched) with the number of samples that takes the GMM "
        f"method's run time (rate measured on a {200_000 if not args.quick else 20_000}-sample pilot, "
        f"{rate * 1e6:.3g} µs per sample), against the reference; max relative error of J_n^{{-1}} over n = 1..{T}. "
        "The paper compares its GMM with a 1.2e4-sample MC of about the GMM's run time *excluding* k-means "
        "(4.157 s) and finds the GMM more accurate. Here, at equal total time (k-means included), the "
        + " and ".join(
            f"{'Monte Carlo' if r[-1] == 'MC' else 'GMM'} is more accurate against {r[0]}" for r in eq_rows
        )
        + f" (the reference's own max relative standard error is {mc_rel_se:.1e}, so errors below about "
        f"{2 * mc_rel_se:.1e} are not resolved).",
        "",
        markdown_table(
            [
                "GMM configuration",
                "GMM run s",
                "GMM max rel. err.",
                "MC samples (same time)",
                "MC run s",
                "MC max rel. err.",
                "more accurate",
            ],
            eq_rows,
        ),
        "",
        *([f"![PCRB accuracy at equal time]({png.name})", ""] if png else []),
        sat_md,
    ]
    print("\n".join(md))
    path = write_results("pcrb", data, "\n".join(md), quick=args.quick)
    print(f"\nwrote {path}")
    return data


if __name__ == "__main__":
    main()
