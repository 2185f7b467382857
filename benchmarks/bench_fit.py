"""Learning a filter's parameters with ``gmjax.fit`` (issue 45): speed and accuracy against references.

``gmjax.fit`` runs an optax optimiser (default ``optax.lbfgs()``, zoom line search) in one compiled
step per iteration until the loss stops moving. For each case the benchmark reports the compile time
of that step (``FitResult.compile_s``, apart from the run time), the seconds per fitting step
(``run_s / n_steps``: the step's wall time, line search and the per-step host sync included; min and
median over repeated fits where the fit is repeated), the steps taken, the convergence flag and the
fitted values beside a reference.

1. **Kalman filter noise variances by maximum likelihood** (the setting of ``tests/fitting/test_fitting.py``):
   scalar ``x_k = 0.95 x_{k-1} + w``, ``z = x + v``, true ``Q = 0.3``, ``R = 1.5``, ``x_0 ~ N(0, 4)``,
   3 sequences of 80 steps, ``fit=["Q", "R"]`` from ``Q = R = 1``. References:
   ``references/kalman_np.py``'s ``ml_noise_variances`` (exact likelihood, scipy Nelder-Mead
   + BFGS + Newton polish): its optimum (relative difference of gmjax's) and its wall time; a minimal
   hand-written JAX kernel of the same work (``jit`` of ``value_and_grad`` of a scalar Kalman
   log-likelihood in ``lax.scan``, ``vmap`` over the sequences, softplus-unconstrained ``(Q, R)``, one
   ``optax.lbfgs`` update with the same line search), driven by the same Python loop and convergence
   rule, timed per step in alternating rounds with gmjax (``gmjax / minimal``); and one exact NumPy
   likelihood evaluation (``kalman_np.kalman_loglik_batch``), whose time over gmjax's time per step is
   the ``x NumPy`` column (a NumPy step would need more than one evaluation: a finite-difference
   gradient and a line search).
2. **A GSF's Gaussian-mixture measurement noise by maximum likelihood**: scalar ``x_k = 0.9 x_{k-1} + w``
   (``q = 0.1``), ``z = x + v``, ``v`` a 2-component mixture (weights 0.3/0.7, means -2/1,
   variances 0.3/0.6: components separated by about 4 standard deviations of the innovation, so 300
   steps identify them; with the overlapping mixture of ``tests/fitting/test_reference_gm_noise.py``, q = 0.5,
   means -1.5/0.8, variances 0.4/1.2, the fits equal the grid ML but the ML estimator itself is biased
   at T = 300: 2.4-3.7 standard errors on 20 data sets, seeds 100..119, measured 2026-12-06),
   ``x_0 ~ N(0, 2)``, ``T = 300``; KF-based GSF with Runnalls reduction to 6
   components, ``fit=["model.measurement_noise"]`` from weights 0.5/0.5, means -1/1, variances 1/1.
   Reference (``references/gm_noise_np.py``): on the first data set the point-mass-grid
   likelihood (exact to rounding on a grid of 201 points over +-14 stationary standard deviations: the
   narrowest width involved, the posterior's std ~0.3, is ~3 grid spacings; the 301-point grid checks
   it) maximised by ``ml_fit_grid`` (full mode only: minutes), beside gmjax's fitted
   mixture; the grid NLL at gmjax's fitted parameters against gmjax's loss (the GSF's likelihood
   approximation error; also at the grid optimum), and one grid-likelihood evaluation's time against
   gmjax's time per step. Then 20 independent data sets (``numpy.random.default_rng(seed)``, seeds
   0..19): mean +- standard error of each fitted parameter (components sorted by mean) beside the truth
   and its distance from the truth in standard errors; steps to converge (median, max).
3. **A reducer threshold fitted through a study loss**: the GSF (EKF, capacity 20) with
   ``PruneThreshold(threshold=0.4, mode="soft", temperature=0.1)`` on the seed 000 scalar
   measurement-jump system (``jump_system(n_steps=40)``); ``fit=["reducer.threshold"]`` on the ARMSE of
   training runs (``fitting.study(armse_loss(), n_runs)``, key 1, the same runs every step),
   threshold constrained to (1e-4, 0.9). Held out (a key never used in training, 400 runs): the *hard*
   filter at the default 0.4 and at the fitted threshold on the same simulated runs; ARMSE +- s.e.
   (delta method) and the paired difference +- its s.e.

Usage: python benchmarks/bench_fit.py [--quick] [--repeats 5] [--gm-datasets 20] [--train-runs 64]
       [--eval-runs 400] [--no-grid-fit]   (or: gmjax bench fit [--quick] ...)
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # references/

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402
from _common import (  # noqa: E402
    RESULTS_DIR,
    block,
    markdown_table,
    per_run_contrib,
    time_alternating,
    time_python,
    write_results,
)

import gmjax  # noqa: E402
from gmjax import GaussianMixture, filters, fitting, montecarlo, reduction  # noqa: E402
from gmjax.models import StateSpaceModel  # noqa: E402
from gmjax.scenarios.jump_system import jump_system  # noqa: E402
from references import gm_noise_np, kalman_np  # noqa: E402

# case 1
KF_F, KF_Q, KF_R, KF_P0, KF_B, KF_T = 0.95, 0.3, 1.5, 4.0, 3, 80
# case 2
GM_A, GM_Q, GM_M0, GM_P0, GM_T = 0.9, 0.1, 0.0, 2.0, 300
GM_W, GM_MU, GM_S2 = np.array([0.3, 0.7]), np.array([-2.0, 1.0]), np.array([0.3, 0.6])
GM_START = ([0.5, 0.5], [-1.0, 1.0], [1.0, 1.0])
GM_GRID_POINTS, GM_GRID_SD = 201, 14.0
GM_CHECK_POINTS = 301  # a finer grid, to check the 201-point likelihood
NOISE = "model.measurement_noise"
# case 3
JUMP_STEPS, JUMP_CAPACITY, THR_DEFAULT, THR_TEMPERATURE, THR_BOUNDS = 40, 20, 0.4, 0.1, (1e-4, 0.9)
TRAIN_SEED = 1
HELDOUT_SEED = 20_261_123  # never used for training


def _converged(losses, gmaxs, gtol=1e-8, ftol=1e-12):
    """gmjax.fit's convergence rule (module docstring of gmjax.fitting), for the minimal kernel's loop."""
    if gmaxs[-1] <= gtol:
        return True
    if len(losses) < 4:
        return False
    last = losses[-4:]
    scale = max(1.0, abs(last[-1]))
    return all(abs(a - b) <= ftol * scale for a, b in zip(last, last[1:]))


def _rel(a, b):
    return abs(a - b) / abs(b)


# ----------------------------------------------------------------------------- case 1: KF Q, R


def kf_data() -> np.ndarray:
    """The data of tests/fitting/test_fitting.py: 3 sequences of 80 steps, rng seed 0."""
    F, H = np.array([[KF_F]]), np.array([[1.0]])
    rng = np.random.default_rng(0)
    zs = np.empty((KF_B, KF_T, 1))
    for b in range(KF_B):
        x = rng.normal(0, 2, 1)
        for t in range(KF_T):
            x = F @ x + rng.normal(0, np.sqrt(KF_Q), 1)
            zs[b, t] = H @ x + rng.normal(0, np.sqrt(KF_R), 1)
    return zs


def minimal_kf_step():
    """The minimal kernel: ``(u, state, zs) -> (u, state, loss, max|grad|)``, one jitted L-BFGS step on the
    per-step NLL of a hand-written scalar Kalman filter, ``(Q, R) = softplus(u)``."""
    opt = optax.lbfgs()

    def nll(u, zs):
        q, r = jax.nn.softplus(u[0]), jax.nn.softplus(u[1])

        def one(z):
            def step(carry, zk):
                m, p = carry
                m, p = KF_F * m, KF_F * p * KF_F + q
                s = p + r
                e = zk - m
                k = p / s
                return (m + k * e, (1.0 - k) * p), -0.5 * (jnp.log(2 * jnp.pi * s) + e * e / s)

            _, ll = jax.lax.scan(step, (jnp.zeros(()), jnp.asarray(KF_P0)), z)
            return ll.sum()

        return -jnp.sum(jax.vmap(one)(zs)) / zs.size

    @jax.jit
    def step(u, state, zs):
        v, g = jax.value_and_grad(nll)(u, zs)
        updates, state = opt.update(g, state, u, value=v, grad=g, value_fn=lambda w: nll(w, zs))
        return optax.apply_updates(u, updates), state, v, jnp.max(jnp.abs(g))

    x0 = jnp.array([1.0, 1.0])
    u0 = x0 + jnp.log(-jnp.expm1(-x0))  # softplus^-1
    return step, opt.init, u0, nll


def minimal_fit(step, init, u0, zs, max_steps=200):
    """The minimal kernel's fitting loop (host sync per step, gmjax's convergence rule)."""
    u, state = u0, init(u0)
    losses, gmaxs = [], []
    t0 = time.perf_counter()
    for _ in range(max_steps):
        u, state, v, g = step(u, state, zs)
        losses.append(float(v))
        gmaxs.append(float(g))
        if _converged(losses, gmaxs):
            break
    run_s = time.perf_counter() - t0
    return {
        "run_s": run_s,
        "n_steps": len(losses),
        "converged": _converged(losses, gmaxs),
        "values": np.asarray(jax.nn.softplus(u)),
        "loss": losses[-1],
    }


def kf_section(args) -> dict:
    zs = kf_data()
    F, H, m0, P0 = np.array([[KF_F]]), np.array([[1.0]]), np.zeros(1), KF_P0 * np.eye(1)
    print("[case 1] KF noise variances: scipy reference ...", flush=True)
    t0 = time.perf_counter()
    q_ref, r_ref, ref = kalman_np.ml_noise_variances(zs, F, H, m0, P0, 1.0, 1.0, np.eye(1), np.eye(1))
    scipy_s = time.perf_counter() - t0
    scipy_evals = int(ref.nelder_mead.nfev + ref.nfev + 8 * ref.njev)  # lower bound (Newton polish left out)
    nll_ref = -ref.loglik / zs[..., 0].size

    kf = filters.kalman_filter(F, H, np.eye(1), np.eye(1), m0, P0)
    print("[case 1] gmjax.fit (compiling) ...", flush=True)
    t0 = time.perf_counter()
    res = gmjax.fit(kf, zs, fit=["Q", "R"], key=jax.random.key(0), progress=False)
    first_call_s = time.perf_counter() - t0
    q_fit, r_fit = float(res.values["Q"][0, 0]), float(res.values["R"][0, 0])

    step, init, u0, minimal_nll = minimal_kf_step()
    zs_j = jnp.asarray(zs[..., 0])
    t0 = time.perf_counter()
    block(step(u0, init(u0), zs_j))
    minimal_first_s = time.perf_counter() - t0
    mini = minimal_fit(step, init, u0, zs_j)  # warm

    # alternating rounds: one gmjax fit and one minimal-kernel fit per round
    g_step, m_step, g_call = [], [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        r = gmjax.fit(kf, zs, fit=["Q", "R"], key=jax.random.key(0), progress=False)
        g_call.append(time.perf_counter() - t0)
        g_step.append(r.run_s / r.n_steps)
        mini = minimal_fit(step, init, u0, zs_j)
        m_step.append(mini["run_s"] / mini["n_steps"])
    minimal_compile_s = max(minimal_first_s - statistics.median(m_step), 0.0)
    # where the time goes: the objective's value_and_grad alone (gmjax's through the public loss_fn)
    view = fitting.param_view(kf.params, ["Q", "R"])
    objective = fitting.loss_fn(kf, zs, fitting.nll(), view)
    u_g = view.unconstrained()
    vg_g = jax.jit(jax.value_and_grad(lambda u: objective(u, jax.random.key(0))))
    vg_m = jax.jit(jax.value_and_grad(minimal_nll))
    vg = time_alternating([lambda: vg_g(u_g), lambda: vg_m(u0, zs_j)], repeats=args.vg_repeats)
    np_eval = time_python(
        kalman_np.kalman_loglik_batch, zs, F, H, KF_Q * np.eye(1), KF_R * np.eye(1), m0, P0, repeats=20
    )
    g_med = statistics.median(g_step)
    m_med = statistics.median(m_step)
    out = {
        "setup": f"x_k = {KF_F} x_(k-1) + w, z = x + v, Q = {KF_Q}, R = {KF_R}, x_0 ~ N(0, {KF_P0}); "
        f"{KF_B} sequences x {KF_T} steps (tests/fitting/test_fitting.py data); fit Q, R from 1, 1",
        "gmjax": {
            "compile_s": res.compile_s,
            "first_call_s": first_call_s,
            "step_s_min": min(g_step),
            "step_s_median": g_med,
            "fit_call_s_median": statistics.median(g_call),
            "n_steps": res.n_steps,
            "converged": bool(res.converged),
            "Q": q_fit,
            "R": r_fit,
            "loss": float(res.loss),
            "loss_history": res.history.loss,
        },
        "scipy": {
            "Q": q_ref,
            "R": r_ref,
            "nll_per_step": nll_ref,
            "wall_s": scipy_s,
            "likelihood_evals_at_least": scipy_evals,
        },
        "rel_diff": {"Q": _rel(q_fit, q_ref), "R": _rel(r_fit, r_ref)},
        "minimal": {
            "compile_s": minimal_compile_s,
            "step_s_min": min(m_step),
            "step_s_median": m_med,
            "n_steps": mini["n_steps"],
            "converged": bool(mini["converged"]),
            "Q": float(mini["values"][0]),
            "R": float(mini["values"][1]),
        },
        "value_and_grad_only": {
            "gmjax_s_min": vg[0]["run_min_s"],
            "gmjax_s_median": vg[0]["run_median_s"],
            "minimal_s_min": vg[1]["run_min_s"],
            "minimal_s_median": vg[1]["run_median_s"],
            "ratio_median": vg[0]["run_median_s"] / vg[1]["run_median_s"],
            "repeats": args.vg_repeats,
        },
        "numpy_eval_s_min": np_eval["run_min_s"],
        "numpy_eval_s_median": np_eval["run_median_s"],
        "gmjax_over_minimal": g_med / m_med,
        "numpy_eval_over_gmjax_step": np_eval["run_median_s"] / g_med,
        "repeats": args.repeats,
    }
    print(
        f"[case 1] gmjax Q = {q_fit:.8f}, R = {r_fit:.8f} ({res.n_steps} steps, converged {res.converged}); "
        f"scipy Q = {q_ref:.8f}, R = {r_ref:.8f}; {1e3 * g_med:.3f} ms/step, minimal {1e3 * m_med:.3f} ms/step",
        flush=True,
    )
    return out


# ----------------------------------------------------------------------------- case 2: GM noise


def gm_simulate(seed: int, T: int = GM_T) -> np.ndarray:
    """One ``(T,)`` measurement sequence of the case-2 system, ``numpy.random.default_rng(seed)``."""
    rng = np.random.default_rng(seed)
    x = rng.normal(GM_M0, math.sqrt(GM_P0))
    zs = np.empty(T)
    for t in range(T):
        x = GM_A * x + rng.normal(0.0, math.sqrt(GM_Q))
        j = rng.choice(2, p=GM_W)
        zs[t] = x + rng.normal(GM_MU[j], math.sqrt(GM_S2[j]))
    return zs


def gm_filter():
    a, q, m0, p0 = GM_A, GM_Q, GM_M0, GM_P0
    w0, mu0, s0 = GM_START
    model = StateSpaceModel(
        f=lambda x, t: a * x,
        h=lambda x, t: x,
        process_noise=GaussianMixture.create([1.0], [[0.0]], [[[q]]]),
        measurement_noise=GaussianMixture.create(w0, [[m] for m in mu0], [[[s]] for s in s0]),
        prior=GaussianMixture.create([1.0], [[m0]], [[[p0]]]),
    )
    return filters.build_gsf(model, "kf", reduction.Runnalls(num_out=6), capacity=6)


def _sorted_mixture(w, mu, s2):
    w, mu, s2 = (np.asarray(v, float).reshape(-1) for v in (w, mu, s2))
    o = np.argsort(mu, kind="stable")
    return w[o], mu[o], s2[o]


def _fitted_mixture(res):
    v = res.values
    return _sorted_mixture(v[f"{NOISE}.weights"], v[f"{NOISE}.means"], v[f"{NOISE}.covs"])


def gm_section(args) -> dict:
    gsf = gm_filter()
    T = GM_T
    sd = math.sqrt(GM_Q / (1 - GM_A**2))
    grid = np.linspace(-GM_GRID_SD * sd, GM_GRID_SD * sd, GM_GRID_POINTS)
    grid_fine = np.linspace(-GM_GRID_SD * sd, GM_GRID_SD * sd, GM_CHECK_POINTS)

    def grid_nll(zs, w, mu, s2, g=grid):
        return -gm_noise_np.grid_loglik(zs, GM_A, GM_Q, w, mu, s2, GM_M0, GM_P0, g) / len(zs)

    @jax.jit
    def gsf_nll(params, zs):
        return -filters.run(gsf, zs, key=jax.random.key(0), params=params)[1].loglik.sum() / zs.shape[0]

    def params_with(w, mu, s2):
        noise = GaussianMixture.create(list(w), [[m] for m in mu], [[[s]] for s in s2])
        return gsf.params._replace(model=gsf.params.model._replace(measurement_noise=noise))

    fits = []
    for i in range(args.gm_datasets):
        zs = gm_simulate(i)
        print(f"[case 2] GSF mixture noise, data set {i} (seed {i}) ...", flush=True)
        res = gmjax.fit(gsf, zs[:, None], fit=[NOISE], key=jax.random.key(0), progress=False, steps=300)
        w, mu, s2 = _fitted_mixture(res)
        fits.append(
            {
                "seed": i,
                "weights": w,
                "means": mu,
                "variances": s2,
                "loss": float(res.loss),
                "n_steps": res.n_steps,
                "converged": bool(res.converged),
                "compile_s": res.compile_s,
                "run_s": res.run_s,
                "step_s": res.run_s / res.n_steps,
                "loss_history": res.history.loss,
            }
        )
    steps_per_fit = [f["step_s"] for f in fits]

    # the first data set against the grid likelihood
    zs0 = gm_simulate(0)
    f0 = fits[0]
    nll_gsf_at_fit = float(gsf_nll(params_with(f0["weights"], f0["means"], f0["variances"]), zs0[:, None]))
    nll_grid_at_fit = grid_nll(zs0, f0["weights"], f0["means"], f0["variances"])
    nll_fine_at_fit = grid_nll(zs0, f0["weights"], f0["means"], f0["variances"], grid_fine)
    grid_eval = time_python(grid_nll, zs0, f0["weights"], f0["means"], f0["variances"], repeats=5)
    first = {
        "seed": 0,
        "gmjax": {k: f0[k] for k in ("weights", "means", "variances", "loss", "n_steps", "converged")},
        "gsf_nll_at_gmjax_fit": nll_gsf_at_fit,
        "grid_nll_at_gmjax_fit": nll_grid_at_fit,
        "grid_nll_at_gmjax_fit_301_points": nll_fine_at_fit,
        "gsf_minus_grid_at_gmjax_fit": nll_gsf_at_fit - nll_grid_at_fit,
        "grid_eval_s_min": grid_eval["run_min_s"],
        "grid_eval_s_median": grid_eval["run_median_s"],
        "gmjax_step_s": f0["step_s"],
        "grid": {
            "points": GM_GRID_POINTS,
            "half_width_stationary_sd": GM_GRID_SD,
            "half_width": GM_GRID_SD * sd,
        },
        "grid_fit": None,
    }
    if args.grid_fit:
        print("[case 2] grid maximum likelihood (ml_fit_grid) on data set 0 ...", flush=True)
        t0 = time.perf_counter()
        ml = gm_noise_np.ml_fit_grid(zs0, GM_A, GM_Q, GM_M0, GM_P0, grid, *GM_START)
        grid_fit_s = time.perf_counter() - t0
        gw, gmu, gs2 = ml["weights"], ml["means"], ml["variances"]
        nll_grid_opt = -ml["loglik"] / T
        nll_gsf_at_opt = float(gsf_nll(params_with(gw, gmu, gs2), zs0[:, None]))
        first["grid_fit"] = {
            "weights": gw,
            "means": gmu,
            "variances": gs2,
            "nll_per_step": nll_grid_opt,
            "nll_per_step_301_points": grid_nll(zs0, gw, gmu, gs2, grid_fine),
            "gsf_nll_at_grid_optimum": nll_gsf_at_opt,
            "gsf_minus_grid_at_grid_optimum": nll_gsf_at_opt - nll_grid_opt,
            "grid_nll_at_gmjax_minus_optimum": nll_grid_at_fit - nll_grid_opt,
            "max_abs_param_diff": float(
                max(
                    np.max(np.abs(f0["weights"] - gw)),
                    np.max(np.abs(f0["means"] - gmu)),
                    np.max(np.abs(f0["variances"] - gs2)),
                )
            ),
            "wall_s": grid_fit_s,
            "evals": int(ml["nelder_mead"].nfev + ml["result"].nfev + 20 * ml["result"].njev),
            "max_abs_grad": float(np.max(np.abs(ml["grad"]))),
        }

    # the data sets together: mean +- s.e. against the truth
    n = len(fits)
    truth = {
        "w1": GM_W[0],
        "w2": GM_W[1],
        "mu1": GM_MU[0],
        "mu2": GM_MU[1],
        "s2_1": GM_S2[0],
        "s2_2": GM_S2[1],
    }
    est = {
        "w1": [f["weights"][0] for f in fits],
        "w2": [f["weights"][1] for f in fits],
        "mu1": [f["means"][0] for f in fits],
        "mu2": [f["means"][1] for f in fits],
        "s2_1": [f["variances"][0] for f in fits],
        "s2_2": [f["variances"][1] for f in fits],
    }
    params = {}
    for k, vals in est.items():
        vals = np.asarray(vals)
        mean = float(vals.mean())
        se = float(vals.std(ddof=1) / math.sqrt(n)) if n > 1 else float("nan")
        params[k] = {
            "truth": float(truth[k]),
            "mean": mean,
            "se": se,
            "sd": float(vals.std(ddof=1)) if n > 1 else float("nan"),
            "z": (mean - truth[k]) / se if n > 1 and se > 0 else float("nan"),
        }
    n_steps = [f["n_steps"] for f in fits]
    out = {
        "setup": f"x_k = {GM_A} x_(k-1) + w (q = {GM_Q}), z = x + v, v ~ GM(weights {GM_W.tolist()}, means "
        f"{GM_MU.tolist()}, variances {GM_S2.tolist()}), x_0 ~ N({GM_M0}, {GM_P0}), T = {T}; KF-GSF, Runnalls to 6, "
        f"capacity 6; start weights {GM_START[0]}, means {GM_START[1]}, variances {GM_START[2]}; lbfgs, <= 300 steps",
        "compile_s": fits[0]["compile_s"],
        "n_datasets": n,
        "step_s_median": statistics.median(steps_per_fit),
        "step_s_min": min(steps_per_fit),
        "steps_median": float(np.median(n_steps)),
        "steps_max": int(max(n_steps)),
        "n_converged": int(sum(f["converged"] for f in fits)),
        "params": params,
        "first_dataset": first,
        "fits": fits,
    }
    print(
        f"[case 2] {n} data sets: steps median {out['steps_median']:.0f} max {out['steps_max']}, "
        f"{out['n_converged']} converged, {1e3 * out['step_s_median']:.1f} ms/step",
        flush=True,
    )
    return out


# ----------------------------------------------------------------------------- case 3: threshold


def threshold_section(args) -> dict:
    sc = jump_system(n_steps=JUMP_STEPS)
    soft = reduction.PruneThreshold(threshold=THR_DEFAULT, mode="soft", temperature=THR_TEMPERATURE)
    gsf = filters.build_gsf(sc.model, "ekf", soft, capacity=JUMP_CAPACITY)
    print(f"[case 3] fitting the pruning threshold on {args.train_runs} training runs ...", flush=True)
    res = gmjax.fit(
        gsf,
        sc,
        fitting.study(montecarlo.armse_loss(), n_runs=args.train_runs),
        fit=["reducer.threshold"],
        key=jax.random.key(TRAIN_SEED),
        constraints={"reducer.threshold": THR_BOUNDS},
        steps=args.thr_steps,
        progress=False,
    )
    thr = float(res.values["reducer.threshold"])
    print(f"[case 3] fitted threshold {thr:.6g} ({res.n_steps} steps, converged {res.converged})", flush=True)

    # held out: the hard filter at both thresholds on the same runs, one compiled program per mode; the
    # relaxed (training) filter at both thresholds on the same runs too, for context
    key = jax.random.key(HELDOUT_SEED)
    print(
        f"[case 3] held out: {args.eval_runs} runs, hard (and soft) pruning at {THR_DEFAULT} and {thr:.4g} ...",
        flush=True,
    )
    configs = [
        ("hard", f"hard, default threshold {THR_DEFAULT}", THR_DEFAULT, 0.0),
        ("hard", f"hard, fitted threshold {thr:.4g}", thr, 0.0),
        (
            "soft",
            f"soft (T = {THR_TEMPERATURE}, as trained), threshold {THR_DEFAULT}",
            THR_DEFAULT,
            THR_TEMPERATURE,
        ),
        (
            "soft",
            f"soft (T = {THR_TEMPERATURE}, as trained), fitted threshold {thr:.4g}",
            thr,
            THR_TEMPERATURE,
        ),
    ]
    programs, timing, scores = {}, {}, []
    for mode, _, value, temp in configs:
        red = reduction.PruneThreshold(threshold=jnp.asarray(value), mode=mode, temperature=jnp.asarray(temp))
        filt = filters.build_gsf(sc.model, "ekf", red, capacity=JUMP_CAPACITY)
        if mode not in programs:
            programs[mode] = jax.jit(
                lambda p, f=filt: montecarlo.study_scores(f, sc, args.eval_runs, key, params=p)
            )
        t0 = time.perf_counter()
        scores.append(block(programs[mode](filt.params)))
        timing.setdefault(mode, []).append(time.perf_counter() - t0)
    a0, c0 = per_run_contrib(np.asarray(scores[0].position_sq_error, float))
    n = len(c0)
    rows = []
    for (mode, label, value, temp), sc_i in zip(configs, scores):
        a, c = per_run_contrib(np.asarray(sc_i.position_sq_error, float))
        rows.append(
            {
                "config": label,
                "mode": mode,
                "temperature": temp,
                "threshold": value,
                "armse": a,
                "armse_se": float(np.std(c, ddof=1) / math.sqrt(n)),
                "diff_vs_hard_default": a - a0,
                "diff_se": float(np.std(c - c0, ddof=1) / math.sqrt(n)),
                "components": float(np.mean(np.asarray(sc_i.n_components))),
            }
        )
    a1 = rows[1]["armse"]
    heldout_first_s, heldout_run_s = timing["hard"]
    h = res.history
    out = {
        "setup": f"seed 000 jump system, {JUMP_STEPS} steps; EKF-GSF, capacity {JUMP_CAPACITY}; PruneThreshold("
        f"threshold={THR_DEFAULT}, mode='soft', temperature={THR_TEMPERATURE}); fit reducer.threshold in "
        f"{THR_BOUNDS} on the position ARMSE of {args.train_runs} training runs (key {TRAIN_SEED}); lbfgs",
        "train_runs": args.train_runs,
        "compile_s": res.compile_s,
        "step_s": res.run_s / res.n_steps,
        "n_steps": res.n_steps,
        "converged": bool(res.converged),
        "threshold": thr,
        "train_loss_start": float(h.loss[0]),
        "train_loss_end": float(res.loss),
        "history": {"loss": h.loss, "threshold": h.values["reducer.threshold"], "grad_max": h.grad_max},
        "heldout": {
            "seed": HELDOUT_SEED,
            "runs": n,
            "rows": rows,
            "diff": a1 - a0,
            "diff_se": rows[1]["diff_se"],
            "compile_plus_run_s": heldout_first_s,
            "run_s": heldout_run_s,
        },
    }
    print(
        f"[case 3] held out ARMSE {a0:.4f} (default) vs {a1:.4f} (fitted), paired difference "
        f"{a1 - a0:+.4f} +- {out['heldout']['diff_se']:.4f}",
        flush=True,
    )
    return out


# ----------------------------------------------------------------------------- report


def _fmt_w(v):
    return "[" + ", ".join(f"{x:.4f}" for x in v) + "]"


def summary_table(d) -> str:
    k, g, t = d["kf"], d["gm"], d["thr"]
    gf = g["first_dataset"]
    kq = k["gmjax"]
    header = ["case", "compile s", "ms / step", "steps", "converged", "fitted", "reference", "vs reference"]
    rows = [
        [
            "1. KF Q, R (ML)",
            f"{kq['compile_s']:.2f}",
            f"{1e3 * kq['step_s_median']:.3f}",
            str(kq["n_steps"]),
            str(kq["converged"]),
            f"Q {kq['Q']:.6f}, R {kq['R']:.6f}",
            f"scipy Q {k['scipy']['Q']:.6f}, R {k['scipy']['R']:.6f}",
            f"rel. diff {max(k['rel_diff'].values()):.1e}",
        ],
        [
            f"2. GSF GM noise (ML), {g['n_datasets']} data sets",
            f"{g['compile_s']:.2f}",
            f"{1e3 * g['step_s_median']:.2f}",
            f"median {g['steps_median']:.0f}, max {g['steps_max']}",
            f"{g['n_converged']}/{g['n_datasets']}",
            "data set 0: w "
            + _fmt_w(gf["gmjax"]["weights"])
            + ", mu "
            + _fmt_w(gf["gmjax"]["means"])
            + ", s2 "
            + _fmt_w(gf["gmjax"]["variances"]),
            (
                "grid ML: w "
                + _fmt_w(gf["grid_fit"]["weights"])
                + ", mu "
                + _fmt_w(gf["grid_fit"]["means"])
                + ", s2 "
                + _fmt_w(gf["grid_fit"]["variances"])
            )
            if gf["grid_fit"]
            else "grid ML not run (--quick)",
            (f"max |param diff| {gf['grid_fit']['max_abs_param_diff']:.2e}; " if gf["grid_fit"] else "")
            + f"NLL GSF - grid at fit {gf['gsf_minus_grid_at_gmjax_fit']:+.1e}",
        ],
        [
            "3. prune threshold (study ARMSE)",
            f"{t['compile_s']:.2f}",
            f"{1e3 * t['step_s']:.1f}",
            str(t["n_steps"]),
            str(t["converged"]),
            f"threshold {t['threshold']:.4g}",
            f"default {THR_DEFAULT}",
            f"held-out ARMSE {t['heldout']['diff']:+.4f} ± {t['heldout']['diff_se']:.4f} (paired)",
        ],
    ]
    return markdown_table(header, rows)


def plot(d, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(13, 3.4))
    lh = np.asarray(d["kf"]["gmjax"]["loss_history"])
    ax[0].semilogy(np.arange(1, len(lh) + 1), np.maximum(lh - d["kf"]["scipy"]["nll_per_step"], 1e-16), ".-")
    ax[0].set(xlabel="step", ylabel="NLL per step - scipy optimum", title="1. KF Q, R")
    for f in d["gm"]["fits"]:
        h = np.asarray(f["loss_history"])
        ax[1].semilogy(np.arange(1, len(h) + 1), np.maximum(h - h.min(), 1e-16), lw=0.8)
    ax[1].set(
        xlabel="step",
        ylabel="NLL per step - final",
        title=f"2. GSF GM noise ({d['gm']['n_datasets']} data sets)",
    )
    th = np.asarray(d["thr"]["history"]["threshold"])
    ax[2].semilogy(np.arange(1, len(th) + 1), th, ".-")
    ax[2].set(xlabel="step", ylabel="threshold", title="3. prune threshold")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: 3 data sets, no grid ML fit, 8 training / 40 held-out runs",
    )
    parser.add_argument(
        "--repeats", type=int, default=None, help="case 1: alternating rounds (default 7; quick 3)"
    )
    parser.add_argument(
        "--gm-datasets", type=int, default=None, help="case 2: data sets (default 20; quick 3)"
    )
    parser.add_argument(
        "--train-runs", type=int, default=None, help="case 3: training runs (default 64; quick 8)"
    )
    parser.add_argument(
        "--thr-steps", type=int, default=None, help="case 3: at most this many steps (100; quick 15)"
    )
    parser.add_argument(
        "--eval-runs", type=int, default=None, help="case 3: held-out runs (default 400; quick 40)"
    )
    parser.add_argument(
        "--no-grid-fit", action="store_true", help="case 2: skip the grid ML fit (skipped with --quick)"
    )
    args = parser.parse_args(argv)
    args.vg_repeats = 50 if args.quick else 300
    q = args.quick
    args.repeats = args.repeats or (3 if q else 7)
    args.gm_datasets = args.gm_datasets or (3 if q else 20)
    args.train_runs = args.train_runs or (8 if q else 64)
    args.thr_steps = args.thr_steps or (15 if q else 100)
    args.eval_runs = args.eval_runs or (40 if q else 400)
    args.grid_fit = not (q or args.no_grid_fit)

    date = subprocess.run(["date"], capture_output=True, text=True).stdout.strip()
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    data = {"kf": kf_section(args), "gm": gm_section(args), "thr": threshold_section(args)}
    data["wall_s"] = time.perf_counter() - t0
    load1 = os.getloadavg()
    data["date"] = date
    data["loadavg_before_after"] = [list(load0), list(load1)]
    data["config"] = {k: v for k, v in vars(args).items()}

    k, g, t = data["kf"], data["gm"], data["thr"]
    md = [
        "# Fitting filter parameters with gmjax.fit (issue 45)",
        "",
        f"Measured {date} on a {os.cpu_count()}-core CPU machine, float64, "
        f"{'quick smoke run' if q else 'full run'}; the machine may have been loaded (other sessions ran tests "
        f"at the same time: load average {' '.join(f'{x:.2f}' for x in load0)} before, "
        f"{' '.join(f'{x:.2f}' for x in load1)} after), so compare ratios measured in the same process rather "
        "than absolute seconds. Compile time (the first fit's `compile_s`) is apart from run time; "
        "seconds per step = `run_s / n_steps` of a fit (the L-BFGS step with its zoom line search and a host "
        "sync per step).",
        "",
        "## Summary",
        "",
        summary_table(data),
        "",
    ]
    kg, km = k["gmjax"], k["minimal"]
    md += [
        "## 1. Kalman filter noise variances by maximum likelihood",
        "",
        k["setup"]
        + ". Minimal kernel: a hand-written scalar Kalman NLL (`lax.scan`, `vmap` over sequences) with "
        "`value_and_grad` and one `optax.lbfgs` update in one `jax.jit`, softplus-unconstrained (Q, R), run by the "
        f"same Python loop and convergence rule. Times per step: {args.repeats} fits of each in alternating rounds "
        "(min / median).",
        "",
        markdown_table(
            [
                "method",
                "Q",
                "R",
                "rel. diff Q / R to scipy",
                "steps",
                "converged",
                "compile s",
                "ms / step (min / median)",
                "time",
            ],
            [
                [
                    "gmjax.fit",
                    f"{kg['Q']:.8f}",
                    f"{kg['R']:.8f}",
                    f"{k['rel_diff']['Q']:.1e} / {k['rel_diff']['R']:.1e}",
                    kg["n_steps"],
                    str(kg["converged"]),
                    f"{kg['compile_s']:.2f}",
                    f"{1e3 * kg['step_s_min']:.3f} / {1e3 * kg['step_s_median']:.3f}",
                    f"{1e3 * kg['fit_call_s_median']:.1f} ms per fit call (warm)",
                ],
                [
                    "minimal JAX kernel",
                    f"{km['Q']:.8f}",
                    f"{km['R']:.8f}",
                    f"{_rel(km['Q'], k['scipy']['Q']):.1e} / {_rel(km['R'], k['scipy']['R']):.1e}",
                    km["n_steps"],
                    str(km["converged"]),
                    f"{km['compile_s']:.2f}",
                    f"{1e3 * km['step_s_min']:.3f} / {1e3 * km['step_s_median']:.3f}",
                    "",
                ],
                [
                    "scipy (kalman_np.ml_noise_variances)",
                    f"{k['scipy']['Q']:.8f}",
                    f"{k['scipy']['R']:.8f}",
                    "-",
                    f">= {k['scipy']['likelihood_evals_at_least']} likelihood evals",
                    "",
                    "",
                    "",
                    f"{k['scipy']['wall_s']:.2f} s per fit",
                ],
            ],
        ),
        "",
        f"gmjax / minimal (time per step): **{k['gmjax_over_minimal']:.2f}x**. One exact NumPy likelihood "
        f"evaluation (`kalman_loglik_batch`, 3 x 80 steps) takes {1e3 * k['numpy_eval_s_median']:.3f} ms "
        f"(median of 20): **x NumPy = {k['numpy_eval_over_gmjax_step']:.2f}** (NumPy evaluation / gmjax step; a "
        "gmjax step also computes the gradient and runs the line search). Fitted NLL per step "
        f"{kg['loss']:.10f} (scipy {k['scipy']['nll_per_step']:.10f}).",
        "",
        f"Where the time goes: the objective's `value_and_grad` alone (jitted, no optimiser; gmjax's through "
        f"`fitting.loss_fn`), {k['value_and_grad_only']['repeats']} calls alternating: gmjax "
        f"{1e6 * k['value_and_grad_only']['gmjax_s_median']:.0f} µs, minimal "
        f"{1e6 * k['value_and_grad_only']['minimal_s_median']:.0f} µs (median; min "
        f"{1e6 * k['value_and_grad_only']['gmjax_s_min']:.0f} / {1e6 * k['value_and_grad_only']['minimal_s_min']:.0f} µs), "
        f"ratio {k['value_and_grad_only']['ratio_median']:.2f}x (per fitting step: {k['gmjax_over_minimal']:.2f}x). "
        "A similar ratio means the gap is the filter's own work at this size (d = m = 1, 3 x 80 steps: general "
        "matrix algebra, checks and flags per time step), not the fitting loop around it.",
        "",
    ]
    gf = g["first_dataset"]
    md += [
        "## 2. A GSF's Gaussian-mixture measurement noise by maximum likelihood",
        "",
        g["setup"] + ".",
        "",
        f"Data set 0 (seed 0) against the point-mass grid likelihood of `reference/gm_noise_np.py` "
        f"({gf['grid']['points']} points on +-{gf['grid']['half_width']:.2f} = +-{GM_GRID_SD:g} stationary std):",
        "",
    ]
    rows = [
        [
            "gmjax.fit (GSF)",
            _fmt_w(gf["gmjax"]["weights"]),
            _fmt_w(gf["gmjax"]["means"]),
            _fmt_w(gf["gmjax"]["variances"]),
            f"{gf['gsf_nll_at_gmjax_fit']:.8f}",
            f"{gf['grid_nll_at_gmjax_fit']:.8f}",
            f"{gf['gmjax']['n_steps']} steps, {1e3 * gf['gmjax_step_s']:.1f} ms / step",
        ]
    ]
    gfit = gf["grid_fit"]
    if gfit:
        rows.append(
            [
                "grid ML (ml_fit_grid)",
                _fmt_w(gfit["weights"]),
                _fmt_w(gfit["means"]),
                _fmt_w(gfit["variances"]),
                f"{gfit['gsf_nll_at_grid_optimum']:.8f}",
                f"{gfit['nll_per_step']:.8f}",
                f"{gfit['wall_s']:.0f} s, >= {gfit['evals']} evals",
            ]
        )
    md += [
        markdown_table(
            ["method", "weights", "means", "variances", "GSF NLL / step", "grid NLL / step", "cost"], rows
        ),
        "",
        f"GSF likelihood approximation error (GSF - grid NLL per step) at gmjax's fit: "
        f"{gf['gsf_minus_grid_at_gmjax_fit']:+.2e}"
        + (f", at the grid optimum: {gfit['gsf_minus_grid_at_grid_optimum']:+.2e}" if gfit else "")
        + f". The 301-point grid gives {gf['grid_nll_at_gmjax_fit_301_points']:.12f} at gmjax's fit "
        f"(201 points: {gf['grid_nll_at_gmjax_fit']:.12f})."
        + (
            f" Largest parameter difference gmjax - grid ML: {gfit['max_abs_param_diff']:.2e}; grid NLL at gmjax's "
            f"fit minus the grid optimum: {gfit['grid_nll_at_gmjax_minus_optimum']:+.2e} per step (largest |grad| of "
            f"the grid log-likelihood at its optimum {gfit['max_abs_grad']:.1e})."
            if gfit
            else " Grid ML fit not run (--quick / --no-grid-fit)."
        )
        + f" One grid-likelihood evaluation takes {1e3 * gf['grid_eval_s_median']:.1f} ms (median of 5) against "
        f"{1e3 * gf['gmjax_step_s']:.1f} ms per gmjax fitting step (value, gradient and line search) on this data "
        f"set (x grid = {gf['grid_eval_s_median'] / gf['gmjax_step_s']:.2f}).",
        "",
        f"{g['n_datasets']} independent data sets (seeds 0..{g['n_datasets'] - 1}), components sorted by mean: "
        f"{g['n_converged']}/{g['n_datasets']} converged, steps median {g['steps_median']:.0f}, max "
        f"{g['steps_max']}; compile {g['compile_s']:.1f} s (once: later fits reuse the step), "
        f"{1e3 * g['step_s_min']:.1f} / {1e3 * g['step_s_median']:.1f} ms per step (min / median over the fits).",
        "",
        markdown_table(
            ["parameter", "truth", "mean ± s.e.", "std over data sets", "(mean - truth) / s.e."],
            [
                [
                    name,
                    f"{p['truth']:.3f}",
                    f"{p['mean']:.4f} ± {p['se']:.4f}",
                    f"{p['sd']:.4f}",
                    f"{p['z']:+.2f}",
                ]
                for name, p in g["params"].items()
            ],
        ),
        "",
    ]
    ho = t["heldout"]
    md += [
        "## 3. A pruning threshold fitted through a study loss",
        "",
        t["setup"] + f": {t['n_steps']} steps (converged {t['converged']}), compile {t['compile_s']:.1f} s, "
        f"{1e3 * t['step_s']:.1f} ms per step; training ARMSE {t['train_loss_start']:.4f} -> {t['train_loss_end']:.4f}, "
        f"fitted threshold {t['threshold']:.4g} (bounds {THR_BOUNDS}).",
        "",
        f"Held out: {ho['runs']} runs (key {ho['seed']}), the same runs for every row (paired). The hard filter "
        f"(mode='hard') at both thresholds (one compiled `study_scores`: compile + first run {ho['compile_plus_run_s']:.1f} s, second run "
        f"{1e3 * ho['run_s']:.0f} ms):",
        "",
        markdown_table(
            [
                "filter",
                "held-out ARMSE ± s.e.",
                "difference to hard default ± paired s.e.",
                "mean components",
            ],
            [
                [
                    r["config"],
                    f"{r['armse']:.4f} ± {r['armse_se']:.4f}",
                    "-" if i == 0 else f"{r['diff_vs_hard_default']:+.4f} ± {r['diff_se']:.4f}",
                    f"{r['components']:.2f}",
                ]
                for i, r in enumerate(ho["rows"])
            ],
        ),
        "",
        "The hard rows are the comparison asked for (the fitted threshold used the way a filter is run); the soft "
        "rows are the relaxed filter the threshold was trained on, at the same thresholds on the same runs.",
        "",
        "Standard errors: the ARMSE's by the delta method over runs; the difference's from the paired per-run "
        "contributions (as in bench_tune.py).",
        "",
    ]
    stem = "fit_quick" if q else "fit"
    png = RESULTS_DIR / f"{stem}.png"
    try:
        plot(data, png)
        md += [f"![fitting histories]({png.name})", ""]
    except ImportError:
        pass
    md += [f"Total wall time {data['wall_s']:.0f} s."]
    path = write_results("fit", data, "\n".join(md), quick=q)
    print("\n".join(md))
    print(f"wrote {path}")
    return data


if __name__ == "__main__":
    main()
