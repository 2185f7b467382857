"""GM-PHD against GM-CPHD on two scenarios: cardinality variance, bias, OSPA and speed (issue 47, item 5).

Scenarios (both filters on the *same* simulated measurement sets of each run):

* ``crossing_targets()``: eight targets on straight tracks (three pairs cross in the middle of the
  region), staggered births and deaths, clutter 30 per scan, ``P_D = 0.9``, four birth sites
  (``gmjax.multitarget.crossing_targets``);
* ``vo_ma_linear()``: Vo & Ma 2006 §VI-A without spawning, clutter 10 per scan, ``P_D = 0.98``.

Filters: ``gm_phd`` and ``gm_cphd`` (``N_max = 30``) with the same reducer (the default Vo–Ma pruning
and merging, ``T = 1e-5``, ``U = 4``, ``J_max`` = capacity) and the same capacities (``J = 50``, 200
components handed to the reducer). Each filter is one jitted program, ``vmap`` over the runs of a
scenario; its compile time (ahead-of-time ``lower().compile()``) is reported apart from its run time
(median of ``--repeats`` calls, alternating PHD and CPHD so a slow spell of the shared machine slows
both alike).

Reported per scenario, over steps ``burn_in + 1 .. T`` (default: steps 6..T, past the start-up):

* the four cardinality estimates: the PHD's mass (``sum w`` of the updated intensity, Vo & Ma eq 29),
  the PHD's Table III count (``n_estimates``), the CPHD's mean and its MAP count (``n_estimates``).
  For each, the variance across runs at every step (``ddof = 1``; the true tracks are deterministic,
  so every run has the same true count at a step), averaged over the steps, with a jackknife (over
  runs) standard error; the paired differences CPHD mean - PHD mass and CPHD MAP - PHD count with
  their jackknife standard errors; the mean bias against the true count with its standard error over
  runs (per-run mean bias); the filter's own reported variance (PHD: the Poisson variance = its mass;
  CPHD: ``cardinality_variance``), averaged;
* OSPA (``c = 100 m``, ``p = 1``, as bench_phd) over time and its per-run average over the steps with
  its standard error over runs, and the paired difference CPHD - PHD;
* time per run-scan (µs) for each filter, the compile times, the flags, the machine load
  (``os.getloadavg`` before and after).

Results: ``benchmarks/results/cphd.json``, ``cphd.md`` and ``cphd.png`` (cardinality mean ± sd over
time against the truth, and OSPA over time, per scenario; skipped with a note without matplotlib).

Usage: python benchmarks/bench_cphd.py [--quick] [--runs N] [--steps T] [--repeats R] [--n-max N]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _common import RESULTS_DIR, block, markdown_table, write_results  # noqa: E402

from gmjax import multitarget as mt  # noqa: E402

C_OSPA, P_OSPA = 100.0, 1.0
CAPACITY, MERGE_CAPACITY, N_MAX = 50, 200, 30
BURN_IN = 5
ESTIMATORS = {
    "phd_mass": "PHD mass (sum w)",
    "phd_count": "PHD count (Table III)",
    "cphd_mean": "CPHD mean",
    "cphd_map": "CPHD MAP count",
}
PAIRS = (("cphd_mean", "phd_mass"), ("cphd_map", "phd_count"))


def scenarios(steps: int) -> dict[str, mt.MultiTargetScenario]:
    """The two scenarios of the study, ``steps`` long."""
    return {
        "crossing_targets": mt.crossing_targets(n_steps=steps),
        "vo_ma_linear": mt.vo_ma_linear(n_steps=steps, clutter_rate=10.0, detection_prob=0.98),
    }


# ----------------------------------------------------------------------------- statistics


def jackknife_se(stat, n_runs: int) -> float:
    """Jackknife standard error over runs of ``stat(selection (n_runs,) bool) -> float`` (NaN below 3 runs)."""
    if n_runs < 3:
        return float("nan")
    vals = np.array([stat(np.arange(n_runs) != i) for i in range(n_runs)])
    return float(np.sqrt((n_runs - 1) / n_runs * np.sum((vals - vals.mean()) ** 2)))


def _mean_se(x: np.ndarray) -> tuple[float, float]:
    """Mean of per-run values ``(N,)`` and its standard error over runs."""
    se = float(x.std(ddof=1) / np.sqrt(len(x))) if len(x) > 1 else float("nan")
    return float(x.mean()), se


def cardinality_stats(estimates: dict[str, np.ndarray], truth: np.ndarray) -> dict:
    """Across-run variance (averaged over steps), bias and MSE of each ``(N, T)`` estimate, with standard
    errors, and the paired variance differences of :data:`PAIRS`."""
    truth = np.asarray(truth, np.float64)
    n_runs = truth.shape[0]
    everyone = np.ones(n_runs, bool)

    def var(x):
        return lambda sel: float(np.mean(np.var(x[sel], axis=0, ddof=1)))

    out: dict = {}
    for name, x in estimates.items():
        x = np.asarray(x, np.float64)
        bias, bias_se = _mean_se((x - truth).mean(1))
        mse, mse_se = _mean_se(((x - truth) ** 2).mean(1))
        out[name] = {
            "var": var(x)(everyone),
            "var_se": jackknife_se(var(x), n_runs),
            "bias": bias,
            "bias_se": bias_se,
            "mse": mse,
            "mse_se": mse_se,
        }
    for a, b in PAIRS:
        xa, xb = (np.asarray(estimates[k], np.float64) for k in (a, b))

        def diff(sel, xa=xa, xb=xb):
            return var(xa)(sel) - var(xb)(sel)

        d, se = diff(everyone), jackknife_se(diff, n_runs)
        out[f"{a}-{b}"] = {"var": d, "var_se": se, "z": d / se if se > 0 else float("nan")}
    return out


# ----------------------------------------------------------------------------- the study


def _slim(infos) -> dict:
    """What the study reads from a filter's ``(N, T)`` infos (keeps the program's output small)."""
    ex = infos.extra
    out = {
        "cardinality": ex["cardinality"],
        "n_estimates": ex["n_estimates"],
        "estimates": ex["estimates"][..., :2],
        "estimate_mask": ex["estimate_mask"],
        "overflow": infos.flags.overflow,
        "reducer_overflow": infos.reduction.overflow,  # Vo-Ma kept its J_max heaviest components
        "truncated_mass": ex["truncated_mass"],
        "degenerate": infos.flags.degenerate,
    }
    if "cardinality_variance" in ex:
        out["cardinality_variance"] = ex["cardinality_variance"]
    return out


def _ospa(est, est_mask, truth, alive) -> np.ndarray:
    """``(N, T)`` OSPA of padded estimate sets against the true positions."""
    f = jax.vmap(jax.vmap(lambda e, em, x, a: mt.ospa(e, x, em, a, c=C_OSPA, p=P_OSPA)))
    return np.asarray(jax.jit(f)(est, est_mask, truth[..., :2], alive))


def run_study(
    sc: mt.MultiTargetScenario,
    *,
    runs: int,
    seed: int = 0,
    n_max: int = N_MAX,
    capacity: int = CAPACITY,
    merge_capacity: int = MERGE_CAPACITY,
    repeats: int = 1,
    burn_in: int = BURN_IN,
) -> dict:
    """Simulate ``runs`` runs of ``sc``, filter them with the GM-PHD and GM-CPHD and score both.

    Returns:
        A JSON-able dict: settings, ``timing`` per filter, ``cardinality`` (:func:`cardinality_stats`),
        ``ospa`` (mean and s.e. per filter, paired difference), flags, and per-step series for the plot.
    """
    T = int(sc.n_steps)
    start = min(int(burn_in), T - 1)
    keys = jax.random.split(jax.random.PRNGKey(seed), runs)
    samples = jax.jit(jax.vmap(lambda k: mt.simulate(sc, k)))(keys)
    block(samples)
    kw = dict(capacity=capacity, merge_capacity=merge_capacity)
    filters = {
        "phd": mt.gm_phd(sc.model, **sc.filter_kwargs(), **kw),
        "cphd": mt.gm_cphd(sc.model, **sc.filter_kwargs(), n_max=n_max, **kw),
    }
    compiled, timing = {}, {}
    for name, f in filters.items():
        prog = jax.jit(jax.vmap(lambda z, f=f: _slim(mt.run(f, z)[1])))
        t0 = time.perf_counter()
        compiled[name] = prog.lower(samples.zs).compile()
        timing[name] = {"compile_s": time.perf_counter() - t0, "runs_s": []}
    outs = {}
    for _ in range(max(1, repeats)):  # alternate the filters: a slow spell slows both alike
        for name, prog in compiled.items():
            t0 = time.perf_counter()
            outs[name] = block(prog(samples.zs))
            timing[name]["runs_s"].append(time.perf_counter() - t0)
    for tm in timing.values():
        tm["run_median_s"] = float(np.median(tm["runs_s"]))
        tm["run_min_s"] = float(np.min(tm["runs_s"]))
        tm["us_per_run_scan"] = 1e6 * tm["run_median_s"] / (runs * T)
    outs = {k: {n: np.asarray(a) for n, a in v.items()} for k, v in outs.items()}
    truth = np.asarray(samples.alive).sum(-1).astype(np.float64)  # (N, T)
    raw = {
        "phd_mass": outs["phd"]["cardinality"],
        "phd_count": outs["phd"]["n_estimates"],
        "cphd_mean": outs["cphd"]["cardinality"],
        "cphd_map": outs["cphd"]["n_estimates"],
    }
    window = {k: np.asarray(v, np.float64)[:, start:] for k, v in raw.items()}
    card = cardinality_stats(window, truth[:, start:])
    card["phd_mass"]["reported_var"] = float(window["phd_mass"].mean())  # Poisson: variance = mean
    card["cphd_mean"]["reported_var"] = float(outs["cphd"]["cardinality_variance"][:, start:].mean())
    ospa = {
        k: _ospa(outs[k]["estimates"], outs[k]["estimate_mask"], np.asarray(samples.states), samples.alive)
        for k in filters
    }
    per_run = {k: v[:, start:].mean(1) for k, v in ospa.items()}
    ospa_summary = {}
    for k, v in per_run.items():
        m, se = _mean_se(v)
        ospa_summary[k] = {"mean": m, "se": se}
    m, se = _mean_se(per_run["cphd"] - per_run["phd"])
    ospa_summary["cphd-phd"] = {"mean": m, "se": se}
    series = {
        "true_cardinality": truth[0].tolist(),
        **{f"{k}_mean": np.asarray(v, np.float64).mean(0).tolist() for k, v in raw.items()},
        **{
            f"{k}_sd": (np.asarray(v, np.float64).std(0, ddof=1) if runs > 1 else np.zeros(T)).tolist()
            for k, v in raw.items()
        },
        **{f"ospa_{k}": v.mean(0).tolist() for k, v in ospa.items()},
    }
    flags = {
        f"{k}_{flag}_steps": int(outs[k][flag].sum())
        for k in filters
        for flag in ("overflow", "reducer_overflow", "degenerate")
    }
    flags.update({f"{k}_max_truncated_mass": float(outs[k]["truncated_mass"].max()) for k in filters})
    flags["scan_overflow_steps"] = int(np.asarray(samples.overflow).sum())
    return {
        "scenario": sc.name,
        "runs": runs,
        "steps": T,
        "window": [start + 1, T],
        "seed": seed,
        "clutter_rate": float(sc.clutter_rate),
        "detection_prob": float(sc.detection_prob),
        "max_measurements": int(sc.max_measurements),
        "n_targets": sc.n_targets,
        "max_true_cardinality": int(truth.max()),
        "n_max": n_max,
        "capacity": capacity,
        "merge_capacity": merge_capacity,
        "timing": timing,
        "cardinality": card,
        "ospa": ospa_summary,
        "flags": flags,
        "series": series,
    }


# ----------------------------------------------------------------------------- report


def _pm(v: float, se: float, digits: int = 4) -> str:
    return f"{v:.{digits}f} ± {se:.{digits}f}"


def verdict(res: dict) -> str:
    """One sentence per pair: is the CPHD's variance below the PHD's by more than 3 standard errors?"""
    parts = []
    for a, b in PAIRS:
        r = res["cardinality"][f"{a}-{b}"]
        d, se = r["var"], r["var_se"]
        if not np.isfinite(se) or se <= 0:
            parts.append(
                f"{ESTIMATORS[a]} - {ESTIMATORS[b]}: {d:+.4f} (no standard error with {res['runs']} runs)"
            )
            continue
        z = d / se
        if z < -3:
            word = "below the PHD's by more than 3 s.e."
        elif z > 3:
            word = "above the PHD's by more than 3 s.e."
        else:
            word = "not separated from the PHD's by 3 s.e."
        parts.append(
            f"{ESTIMATORS[a]} vs {ESTIMATORS[b]}: difference {d:+.4f} ± {se:.4f} ({z:+.1f} s.e.), {word}"
        )
    text = f"**{res['scenario']}** ({res['runs']} runs): CPHD cardinality variance " + "; ".join(parts)
    return text if text.endswith(".") else text + "."


def _flag_text(fl: dict) -> str:
    parts = [
        f"{k.upper()} overflow {fl[f'{k}_overflow_steps']} (of which the reducer's J_max cap, the heaviest "
        f"components kept: {fl[f'{k}_reducer_overflow_steps']}), degenerate {fl[f'{k}_degenerate_steps']}, "
        f"largest mass truncated before the reducer {fl[f'{k}_max_truncated_mass']:.1e}"
        for k in ("phd", "cphd")
    ]
    return "; ".join(parts) + f"; scans over capacity {fl['scan_overflow_steps']}"


def scenario_markdown(res: dict) -> list[str]:
    c, o, tm = res["cardinality"], res["ospa"], res["timing"]
    md = [
        f"## {res['scenario']}",
        "",
        f"{res['runs']} runs x {res['steps']} steps (statistics over steps {res['window'][0]}..{res['window'][1]}), "
        f"clutter {res['clutter_rate']:g}/scan, P_D = {res['detection_prob']:g}, M = {res['max_measurements']}, "
        f"{res['n_targets']} targets (at most {res['max_true_cardinality']} alive), N_max = {res['n_max']}, "
        f"J = {res['capacity']}, merge capacity {res['merge_capacity']}.",
        "",
    ]
    rows = []
    for k, label in ESTIMATORS.items():
        r = c[k]
        rows.append(
            [
                label,
                _pm(r["var"], r["var_se"]),
                f"{r['reported_var']:.4f}" if "reported_var" in r else "-",
                _pm(r["bias"], r["bias_se"]),
                _pm(r["mse"], r["mse_se"]),
            ]
        )
    md.append(
        markdown_table(
            [
                "estimator",
                "variance across runs",
                "filter's reported variance (mean)",
                "bias vs truth",
                "MSE vs truth",
            ],
            rows,
        )
    )
    md += ["", "Paired differences of the across-run variance (jackknife s.e. over runs):", ""]
    md.append(
        markdown_table(
            ["CPHD - PHD", "variance difference", "in s.e."],
            [
                [
                    f"{ESTIMATORS[a]} - {ESTIMATORS[b]}",
                    _pm(c[f"{a}-{b}"]["var"], c[f"{a}-{b}"]["var_se"]),
                    f"{c[f'{a}-{b}']['z']:+.1f}",
                ]
                for a, b in PAIRS
            ],
        )
    )
    md += ["", verdict(res), ""]
    md.append(
        markdown_table(
            ["filter", "mean OSPA (m)", "compile s", "run s", "µs per run-scan"],
            [
                [
                    name.upper(),
                    _pm(o[name]["mean"], o[name]["se"], 3),
                    f"{tm[name]['compile_s']:.2f}",
                    f"{tm[name]['run_median_s']:.2f}",
                    f"{tm[name]['us_per_run_scan']:.0f}",
                ]
                for name in ("phd", "cphd")
            ],
        )
    )
    ratio = tm["cphd"]["us_per_run_scan"] / tm["phd"]["us_per_run_scan"]
    md += [
        "",
        f"OSPA (c = {C_OSPA:g} m, p = {P_OSPA:g}) paired difference CPHD - PHD: "
        f"{_pm(o['cphd-phd']['mean'], o['cphd-phd']['se'], 3)} m. CPHD / PHD time per run-scan: {ratio:.2f}x. "
        f"Flags (steps of all runs): {_flag_text(res['flags'])}.",
        "",
    ]
    s = res["series"]
    T = res["steps"]
    trow = [
        [
            k + 1,
            s["true_cardinality"][k],
            f"{s['phd_mass_mean'][k]:.3f} ± {s['phd_mass_sd'][k]:.3f}",
            f"{s['cphd_mean_mean'][k]:.3f} ± {s['cphd_mean_sd'][k]:.3f}",
            s["ospa_phd"][k],
            s["ospa_cphd"][k],
        ]
        for k in range(0, T, max(1, T // 10))
    ]
    md.append(
        markdown_table(
            ["step", "true n", "PHD mass (mean ± sd)", "CPHD mean (mean ± sd)", "OSPA PHD", "OSPA CPHD"], trow
        )
    )
    return md + [""]


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    fig, axes = plt.subplots(2, len(names), figsize=(6 * len(names), 6.5), squeeze=False)
    for j, name in enumerate(names):
        s = results[name]["series"]
        steps = np.arange(1, len(s["true_cardinality"]) + 1)
        ax = axes[0, j]
        ax.step(steps, s["true_cardinality"], "k", where="mid", lw=1.2, label="truth")
        for key, color, label in (("phd_mass", "C0", "PHD mass"), ("cphd_mean", "C3", "CPHD mean")):
            m, sd = np.asarray(s[f"{key}_mean"]), np.asarray(s[f"{key}_sd"])
            ax.plot(steps, m, color=color, lw=1, label=f"{label} ± sd")
            ax.fill_between(steps, m - sd, m + sd, color=color, alpha=0.2, lw=0)
        ax.set(xlabel="step", ylabel="cardinality", title=f"{name} ({results[name]['runs']} runs)")
        ax.legend(fontsize=8)
        ax = axes[1, j]
        ax.plot(steps, s["ospa_phd"], "C0", lw=1, label="PHD")
        ax.plot(steps, s["ospa_cphd"], "C3", lw=1, label="CPHD")
        ax.set(xlabel="step", ylabel=f"mean OSPA (m), c = {C_OSPA:g}, p = {P_OSPA:g}")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="smoke run: 8 runs of 30 steps")
    parser.add_argument("--runs", type=int, default=None, help="Monte Carlo runs per scenario (default 100)")
    parser.add_argument("--steps", type=int, default=None, help="steps per run (default 100)")
    parser.add_argument(
        "--crossing-runs",
        type=int,
        default=None,
        help="runs of crossing_targets only (default --runs): its CPHD is the expensive program",
    )
    parser.add_argument("--repeats", type=int, default=1, help="timed calls of each compiled filter")
    parser.add_argument("--n-max", type=int, default=N_MAX, help="the CPHD's N_max")
    parser.add_argument("--burn-in", type=int, default=BURN_IN, help="steps left out of the statistics")
    parser.add_argument("--seed", type=int, default=2007)
    parser.add_argument(
        "--scenarios", nargs="+", default=None, help="a subset of crossing_targets vo_ma_linear"
    )
    parser.add_argument("--note", default="", help="a sentence added to the results (e.g. why N was reduced)")
    args = parser.parse_args(argv)
    q = args.quick
    args.runs = args.runs or (8 if q else 100)
    args.steps = args.steps or (30 if q else 100)
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    results = {}
    for i, (name, sc) in enumerate(scenarios(args.steps).items()):
        if args.scenarios and name not in args.scenarios:
            continue
        runs = args.crossing_runs if name == "crossing_targets" and args.crossing_runs else args.runs
        print(f"{name}: {runs} runs x {args.steps} steps ...", flush=True)
        results[name] = run_study(
            sc,
            runs=runs,
            seed=args.seed + i,
            n_max=args.n_max,
            repeats=args.repeats,
            burn_in=args.burn_in,
        )
        tm = results[name]["timing"]
        print(
            f"  compile PHD {tm['phd']['compile_s']:.1f} s, CPHD {tm['cphd']['compile_s']:.1f} s; run PHD "
            f"{tm['phd']['run_median_s']:.1f} s, CPHD {tm['cphd']['run_median_s']:.1f} s",
            flush=True,
        )
    wall = time.perf_counter() - t0
    load_after = os.getloadavg()
    data = {
        "settings": {
            "runs": args.runs,
            "crossing_runs": args.crossing_runs or args.runs,
            "steps": args.steps,
            "repeats": args.repeats,
            "n_max": args.n_max,
            "capacity": CAPACITY,
            "merge_capacity": MERGE_CAPACITY,
            "reducer": "VoMa(1e-5, 4.0, max_components=capacity) (the filters' default)",
            "ospa": {"c": C_OSPA, "p": P_OSPA},
            "burn_in": args.burn_in,
            "seed": args.seed,
        },
        "load_before": list(load_before),
        "load_after": list(load_after),
        "note": args.note,
        "scenarios": results,
        "wall_s": wall,
    }
    md = [
        "# GM-PHD vs GM-CPHD: cardinality variance, bias, OSPA and speed (issue 47, item 5)",
        "",
        f"Machine load (1/5/15-min averages, {os.cpu_count()} cores) before {tuple(round(x, 2) for x in load_before)}, "
        f"after {tuple(round(x, 2) for x in load_after)}: timings were taken on a shared, loaded CPU machine; "
        "compare ratios, not absolute seconds.",
        "",
        "Both filters run on the same simulated measurement sets, each one jitted program vmapped over the runs "
        f"(compile time apart), the same reducer (Vo–Ma T = 1e-5, U = 4) and capacities (J = {CAPACITY}, "
        f"{MERGE_CAPACITY} components to the reducer); CPHD N_max = {args.n_max}. Cardinality estimates: the PHD's "
        "mass (sum of the updated weights, Vo & Ma eq 29) and its Table III count; the CPHD's mean and its MAP count. "
        "'Variance across runs' is the per-step variance over runs (the true tracks are deterministic, so every run "
        "has the same true count at a step) averaged over the steps, ± a jackknife s.e. over runs; bias and MSE "
        "± s.e. over runs. The PHD's own variance is its Poisson variance (= its mass); the CPHD's is the variance "
        "of its cardinality distribution.",
        "",
    ]
    if args.note:
        md += [f"Note: {args.note}", ""]
    for res in results.values():
        md += scenario_markdown(res)
    md += ["## Summary", ""]
    for res in results.values():
        md += [verdict(res), ""]
    stem = "cphd_quick" if q else "cphd"
    png = RESULTS_DIR / f"{stem}.png"
    try:
        RESULTS_DIR.mkdir(parents=True, exist_ok=True)
        plot(results, png)
        md += [f"![cardinality and OSPA over time]({png.name})", ""]
    except ImportError:
        print("matplotlib not installed: no plot")
    md += [f"Wall time {wall:.0f} s."]
    path = write_results("cphd", data, "\n".join(md), quick=q)
    print("\n".join(md))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
