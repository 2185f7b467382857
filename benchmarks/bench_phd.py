"""GM-PHD Monte Carlo: gmjax (vmap over runs, one compiled kernel) against Stone Soup's loop (issue 21).

Scenario: Vo & Ma 2006 §VI-A linear example without spawning (``gmjax.multitarget.vo_ma_linear``):
2-D CV targets, ``P_S = 0.99``, ``P_D = 0.98``, clutter 10 per scan uniform over ``[-1000, 1000]^2``,
births ``0.1 N(±[250, 250, 0, 0], diag(100, 100, 25, 25))``, Vo–Ma pruning ``T = 1e-5`` and merging
``U = 4``, ``J_max = 50`` (the paper: 100), 100 steps, four targets born at steps 1, 1, 20, 40, two
dying at 70 and 85.

1. **Throughput.** gmjax filters ``N`` simulated runs in one ``jit(vmap(run))`` kernel (compile time
   reported apart); Stone Soup's GM-PHD components (``references/phd_stonesoup.py``: the
   tutorial loop of ``GaussianMixtureHypothesiser`` + ``PHDUpdater`` + ``GaussianMixtureReducer``) filter
   the first few of the *same* measurement sets in the same process. Runs/s of both.
2. **Accuracy over time.** Mean OSPA (``c = 100 m``, ``p = 1``) and mean cardinality against the truth,
   for gmjax over all runs and for both libraries on the runs Stone Soup filtered (their difference
   comes from the reducers' conventions, documented in the reference module).
3. **Tuning.** A few Adam steps on ``log T``, ``log U`` of the relaxed Vo–Ma reduction
   (``gmjax.multitarget.RelaxedVoMa``) against the mean relaxed GOSPA² of a small study, then the hard
   filter with the tuned thresholds against the defaults on held-out runs (mean OSPA).

Usage: python benchmarks/bench_phd.py [--quick] [--runs N] [--stonesoup-runs N] [--tune-steps N]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import markdown_table, time_jax, write_results  # noqa: E402

from gmjax import multitarget as mt  # noqa: E402

C_OSPA, P_OSPA = 100.0, 1.0
CAPACITY, MERGE_CAPACITY = 50, 200


def _ospa_over_time(est, est_mask, truth, alive):
    """``(N, T)`` OSPA of padded estimate sets against the truth positions."""
    f = jax.vmap(jax.vmap(lambda e, em, x, a: mt.ospa(e, x, em, a, c=C_OSPA, p=P_OSPA)))
    return np.asarray(jax.jit(f)(est[..., :2], est_mask, truth[..., :2], alive))


def throughput_section(args):
    sc = mt.vo_ma_linear(n_steps=args.steps, max_measurements=32)
    keys = jax.random.split(jax.random.PRNGKey(2024), args.runs)
    samples = jax.jit(jax.vmap(lambda k: mt.simulate(sc, k)))(keys)
    f = mt.gm_phd(sc.model, **sc.filter_kwargs(), capacity=CAPACITY, merge_capacity=MERGE_CAPACITY)
    kernel = jax.jit(jax.vmap(lambda z: mt.run(f, z)))
    timing = time_jax(kernel, samples.zs, repeats=args.repeats)
    _, infos = kernel(samples.zs)
    ospa = _ospa_over_time(
        infos.extra["estimates"], infos.extra["estimate_mask"], samples.states, samples.alive
    )
    n_true = np.asarray(samples.alive).sum(-1)
    card = np.asarray(infos.extra["cardinality_reduced"])
    n_est = np.asarray(infos.extra["n_estimates"])
    flags = {
        "overflow_steps": int(np.asarray(infos.flags.overflow).sum()),
        "scan_overflow_steps": int(np.asarray(samples.overflow).sum()),
    }

    # Stone Soup on the first runs, same measurement sets
    ss_section = None
    try:
        from references.phd_stonesoup import StoneSoupGMPHD
        from references.phd_stonesoup import extract as ss_extract
    except ImportError:  # pragma: no cover
        StoneSoupGMPHD = None
    if StoneSoupGMPHD is not None and args.stonesoup_runs > 0:
        try:
            import stonesoup  # noqa: F401
        except ImportError:
            StoneSoupGMPHD = None
    if StoneSoupGMPHD is not None and args.stonesoup_runs > 0:
        model = sc.model
        F = np.asarray(jax.jacfwd(model.f)(jnp.zeros(4), 0))
        H = np.asarray(jax.jacfwd(model.h)(jnp.zeros(4), 0))
        Q, R = np.asarray(model.process_noise.covs[0]), np.asarray(model.measurement_noise.covs[0])
        b = sc.birth
        births = list(zip(np.asarray(b.weights), np.asarray(b.means), np.asarray(b.covs)))
        n_ss = min(args.stonesoup_runs, args.runs)
        zs = np.asarray(samples.zs)
        times, ospa_ss, card_ss, nest_ss = [], [], [], []
        for r in range(n_ss):
            ss = StoneSoupGMPHD(
                F,
                Q,
                H,
                R,
                births,
                survival_prob=sc.survival_prob,
                detection_prob=sc.detection_prob,
                clutter_intensity=sc.clutter_rate * sc.clutter_density,
                max_components=CAPACITY,
            )
            scans = [z[~np.isnan(z[:, 0])] for z in zs[r]]
            t0 = time.perf_counter()
            out = ss.run(scans)
            times.append(time.perf_counter() - t0)
            row, crow, nrow = [], [], []
            for k, comps in enumerate(out):
                est = ss_extract(comps)
                truth = np.asarray(samples.states[r, k])[np.asarray(samples.alive[r, k])]
                if len(est) == 0 and len(truth) == 0:
                    row.append(0.0)
                else:
                    row.append(
                        float(
                            mt.ospa(
                                est[:, :2].reshape(-1, 2), truth[:, :2].reshape(-1, 2), c=C_OSPA, p=P_OSPA
                            )
                        )
                    )
                crow.append(sum(c[0] for c in comps))
                nrow.append(len(est))
            ospa_ss.append(row)
            card_ss.append(crow)
            nest_ss.append(nrow)
        ospa_ss, card_ss = np.array(ospa_ss), np.array(card_ss)
        ss_section = {
            "runs": n_ss,
            "seconds_per_run": float(np.median(times)),
            "runs_per_s": float(1.0 / np.median(times)),
            "mean_ospa": float(ospa_ss.mean()),
            "mean_ospa_gmjax_same_runs": float(ospa[:n_ss].mean()),
            "max_abs_cardinality_diff": float(np.max(np.abs(card_ss - card[:n_ss]))),
            "estimate_count_agreement": float(np.mean(np.array(nest_ss) == n_est[:n_ss])),
            "ospa_over_time": ospa_ss.mean(0).tolist(),
        }
    runs_per_s = args.runs / timing["run_median_s"]
    return {
        "runs": args.runs,
        "steps": args.steps,
        "timing": timing,
        "runs_per_s": runs_per_s,
        "mean_ospa": float(ospa.mean()),
        "ospa_over_time": ospa.mean(0).tolist(),
        "ospa_se_over_time": (ospa.std(0, ddof=1) / np.sqrt(args.runs)).tolist() if args.runs > 1 else None,
        "cardinality_over_time": card.mean(0).tolist(),
        "true_cardinality": n_true[0].tolist(),
        "mean_abs_cardinality_error": float(np.mean(np.abs(n_est - n_true))),
        "flags": flags,
        "stonesoup": ss_section,
    }


def tuning_section(args):
    import optax

    sc = mt.vo_ma_linear(n_steps=args.tune_horizon, max_measurements=24)
    temps = (5e-6, 0.5)  # prune temperature (weight units), merge temperature (squared Mahalanobis units)

    def make(T, U, relaxed):
        red = (
            mt.RelaxedVoMa(T, U, *temps, max_components=20)
            if relaxed
            else mt.RelaxedVoMa(T, U, 0.0, 0.0, max_components=20, mode="hard")
        )
        return mt.gm_phd(sc.model, **sc.filter_kwargs(), capacity=20, merge_capacity=80, reducer=red)

    base = make(1e-5, 4.0, True)
    hard = make(1e-5, 4.0, False)

    def loss(theta, samples):
        T, U = jnp.exp(theta)
        params = base.params._replace(reducer=mt.RelaxedVoMa(T, U, *temps, max_components=20))

        def one(zs, truth, alive):
            states, _ = mt.run(base, zs, params=params)

            def score(post, x, a):
                cand, e = mt.soft_estimates(post, 0.5, 0.05, max_copies=2)
                return mt.soft_gospa(cand[:, :2], x[:, :2], e, a, c=C_OSPA, p=2.0).distance ** 2

            return jnp.mean(jax.vmap(score)(states.intensity, truth, alive))

        return jnp.mean(jax.vmap(one)(samples.zs, samples.states, samples.alive))

    def held_out_ospa(theta, samples):
        T, U = jnp.exp(theta)
        params = hard.params._replace(reducer=mt.RelaxedVoMa(T, U, 0.0, 0.0, max_components=20, mode="hard"))
        _, infos = jax.vmap(lambda z: mt.run(hard, z, params=params))(samples.zs)
        f = jax.vmap(jax.vmap(lambda e, em, x, a: mt.ospa(e, x, em, a, c=C_OSPA, p=P_OSPA)))
        return f(
            infos.extra["estimates"][..., :2],
            infos.extra["estimate_mask"],
            samples.states[..., :2],
            samples.alive,
        )

    sim_sc = jax.jit(jax.vmap(lambda k: mt.simulate(sc, k)))

    def sim(_, keys):
        return sim_sc(keys)

    grad_fn = jax.jit(jax.value_and_grad(loss))
    theta = jnp.log(jnp.array([1e-5, 4.0]))
    opt = optax.adam(args.tune_lr)
    opt_state = opt.init(theta)
    history = []
    t0 = time.perf_counter()
    for i in range(args.tune_steps):
        batch = sim(sc, jax.random.split(jax.random.PRNGKey(100 + i), args.tune_runs))
        val, g = grad_fn(theta, batch)
        history.append(
            {
                "step": i,
                "loss": float(val),
                "T": float(jnp.exp(theta[0])),
                "U": float(jnp.exp(theta[1])),
                "grad": np.asarray(g).tolist(),
            }
        )
        updates, opt_state = opt.update(g, opt_state)
        theta = optax.apply_updates(theta, updates)
    train_s = time.perf_counter() - t0
    held = sim(sc, jax.random.split(jax.random.PRNGKey(999), args.eval_runs))
    ev = jax.jit(held_out_ospa)
    o_def = np.asarray(ev(jnp.log(jnp.array([1e-5, 4.0])), held)).mean(-1)
    o_tun = np.asarray(ev(theta, held)).mean(-1)
    diff = o_tun - o_def
    return {
        "horizon": args.tune_horizon,
        "train_runs": args.tune_runs,
        "steps": args.tune_steps,
        "optimizer": f"adam(lr={args.tune_lr})",
        "temperatures": temps,
        "train_s": train_s,
        "history": history,
        "tuned": {"T": float(jnp.exp(theta[0])), "U": float(jnp.exp(theta[1]))},
        "held_out_runs": args.eval_runs,
        "held_out_ospa_default": float(o_def.mean()),
        "held_out_ospa_tuned": float(o_tun.mean()),
        "paired_diff": float(diff.mean()),
        "paired_diff_se": float(diff.std(ddof=1) / np.sqrt(len(diff))) if len(diff) > 1 else None,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--quick", action="store_true", help="smoke run: 8 runs of 20 steps, 1 Stone Soup run"
    )
    parser.add_argument("--runs", type=int, default=None)
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--stonesoup-runs", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--tune-steps", type=int, default=None)
    parser.add_argument("--tune-runs", type=int, default=None)
    parser.add_argument("--tune-horizon", type=int, default=None)
    parser.add_argument("--eval-runs", type=int, default=None)
    parser.add_argument("--tune-lr", type=float, default=0.2)
    args = parser.parse_args(argv)
    q = args.quick
    args.runs = args.runs or (8 if q else 64)
    args.steps = args.steps or (20 if q else 100)
    args.stonesoup_runs = args.stonesoup_runs if args.stonesoup_runs is not None else (1 if q else 2)
    args.repeats = args.repeats or 1
    args.tune_steps = args.tune_steps if args.tune_steps is not None else (2 if q else 6)
    args.tune_runs = args.tune_runs or (2 if q else 6)
    args.tune_horizon = args.tune_horizon or (10 if q else 30)
    args.eval_runs = args.eval_runs or (4 if q else 32)
    t0 = time.perf_counter()
    data = {"throughput": throughput_section(args)}
    if args.tune_steps > 0:
        data["tuning"] = tuning_section(args)
    data["wall_s"] = time.perf_counter() - t0

    th = data["throughput"]
    ss = th["stonesoup"]
    md = [
        "# GM-PHD Monte Carlo against Stone Soup (issue 21)",
        "",
        "Timings were taken on a shared, loaded 2-core CPU machine (other agents were running tests); "
        "compare ratios, not absolute seconds.",
        "",
        f"Vo & Ma 2006 linear scenario without spawning, {th['steps']} steps, clutter 10/scan, "
        f"J_max = {CAPACITY}, Vo–Ma T = 1e-5, U = 4; OSPA c = {C_OSPA:g} m, p = {P_OSPA:g}.",
        "",
    ]
    rows = [
        [
            "gmjax (jit + vmap)",
            th["runs"],
            th["timing"]["compile_s"],
            th["timing"]["run_median_s"],
            th["runs_per_s"],
            th["mean_ospa"],
        ]
    ]
    if ss:
        rows.append(
            [
                "Stone Soup loop",
                ss["runs"],
                "-",
                ss["seconds_per_run"] * ss["runs"],
                ss["runs_per_s"],
                ss["mean_ospa"],
            ]
        )
    md.append(markdown_table(["filter", "runs", "compile s", "run s", "runs/s", "mean OSPA (m)"], rows))
    if ss:
        md += [
            "",
            f"Speed-up (runs/s): {th['runs_per_s'] / ss['runs_per_s']:.1f}x. On the {ss['runs']} runs "
            f"both filtered: mean OSPA gmjax {ss['mean_ospa_gmjax_same_runs']:.3f} m vs Stone Soup "
            f"{ss['mean_ospa']:.3f} m; max |cardinality difference| {ss['max_abs_cardinality_diff']:.3g} "
            f"(Stone Soup caps merged weights at 1 and redistributes pruned weight); the numbers of "
            f"extracted targets agree in {100 * ss['estimate_count_agreement']:.1f} % of the steps.",
        ]
    else:
        md += ["", "Stone Soup not installed: no comparison."]
    md += [
        "",
        f"gmjax flags: {th['flags']['overflow_steps']} overflow steps, "
        f"{th['flags']['scan_overflow_steps']} scans over capacity; mean |n_est - n_true| "
        f"{th['mean_abs_cardinality_error']:.3f}.",
        "",
        "## OSPA and cardinality over time (every 10th step)",
        "",
    ]
    trow = []
    for k in range(0, th["steps"], max(1, th["steps"] // 10)):
        row = [k + 1, th["true_cardinality"][k], th["cardinality_over_time"][k], th["ospa_over_time"][k]]
        row.append(ss["ospa_over_time"][k] if ss else "-")
        trow.append(row)
    md.append(markdown_table(["step", "true n", "mean PHD mass", "OSPA gmjax", "OSPA Stone Soup"], trow))
    if "tuning" in data:
        tu = data["tuning"]
        md += [
            "",
            "## Tuning T and U by gradient (relaxed Vo–Ma, relaxed GOSPA)",
            "",
            f"{tu['steps']} {tu['optimizer']} steps on {tu['train_runs']} fresh runs each "
            f"({tu['horizon']} steps), temperatures {tu['temperatures']}: T 1e-5 -> {tu['tuned']['T']:.3g}, "
            f"U 4 -> {tu['tuned']['U']:.3g} ({tu['train_s']:.0f} s with compile). Held-out "
            f"({tu['held_out_runs']} paired runs, hard reduction): mean OSPA default "
            f"{tu['held_out_ospa_default']:.3f} m, tuned {tu['held_out_ospa_tuned']:.3f} m, difference "
            f"{tu['paired_diff']:+.3f} ± {tu['paired_diff_se'] or 0:.3f} m.",
            "",
        ]
        md.append(
            markdown_table(
                ["step", "loss", "T", "U"], [[h["step"], h["loss"], h["T"], h["U"]] for h in tu["history"]]
            )
        )
    md += ["", f"Wall time {data['wall_s']:.0f} s."]
    path = write_results("phd", data, "\n".join(md), quick=q)
    print("\n".join(md))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
