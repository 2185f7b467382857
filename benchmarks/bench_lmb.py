"""GM-PHD vs GM-CPHD vs GM-LMB on two scenarios: cardinality, OSPA, track metrics and speed (issue 47, item 5).

Scenarios (the same two as ``bench_cphd.py``; all three filters on the *same* simulated measurement sets
of each run):

* ``crossing_targets()``: eight targets on straight tracks (three pairs cross in the middle of the
  region), staggered births and deaths, clutter 30 per scan, ``P_D = 0.9``, four birth sites;
* ``vo_ma_linear(clutter_rate=10, detection_prob=0.98)``: Vo & Ma 2006 §VI-A without spawning.

Filters (each one jitted program, ``vmap`` over the runs of a scenario; its compile time, ahead of time
with ``lower().compile()``, apart from its run time, the median of ``--repeats`` calls alternating the
three filters so that a slow spell of the shared machine slows all of them alike):

* ``gm_phd`` and ``gm_cphd`` (``N_max = 30``) with capacity 50 and 200 components to the reducer, as
  ``bench_cphd.py``;
* ``gm_lmb`` with ``T = 30`` track slots, ``J = 5`` components per track and ``G = --samples`` Gibbs rows
  (default 500) per update, one PRNG key per run (``jax.random.split``). The scenario's birth weights
  are used as they are: for the PHD/CPHD they are the expected births per step of each birth site, for
  the LMB the existence probability of each birth track (both are read from ``sc.birth.weights`` and
  printed in the results).

Reported per scenario, over steps ``burn_in + 1 .. T`` (default: steps 6..T):

* cardinality: for the PHD's mass and Table III count, the CPHD's mean and MAP count, the LMB's
  ``sum r`` and MAP count, the variance across runs at every step (``ddof = 1``; the true tracks are
  deterministic) averaged over the steps with a jackknife (over runs) standard error, the bias and MSE
  against the true count ± s.e. over runs, and the paired variance differences LMB - CPHD and LMB - PHD
  with jackknife standard errors;
* OSPA (``c = 100 m``, ``p = 1``, per-scan sets, ``bench_cphd._ospa``): the per-run average over the
  steps, mean ± s.e. over runs, for the three filters and the paired differences;
* LMB only (its estimates carry labels): OSPA^(2) (:func:`gmjax.multitarget.tracks.ospa2`, ``c = 100 m``,
  ``p = 1``, window 10 scans) averaged over the steps and runs ± s.e. over runs; label switches and
  fragmentations per run (:func:`gmjax.multitarget.tracks.label_switches`, gate 100 m, positions
  ``sc.position_dims``), counted over every scan of a run, mean ± s.e. and total; the mean (and largest)
  number of distinct Gibbs hypotheses per update;
* time per run-scan (µs) and compile time per filter, the flags, the machine load (``os.getloadavg``
  before and after).

Results: ``benchmarks/results/lmb.json``, ``lmb.md`` and ``lmb.png`` (``lmb_quick.*`` with ``--quick``);
the plot (cardinality mean ± sd over time against the truth, OSPA and OSPA^(2) over time) is skipped with
a note without matplotlib.

Usage: python benchmarks/bench_lmb.py [--quick] [--runs N] [--steps T] [--samples G] [--repeats R]
    [--seed S] [--scenarios NAME ...] [--crossing-runs N] [--note TEXT]
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

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import RESULTS_DIR, block, markdown_table, write_results  # noqa: E402
from bench_cphd import _mean_se, _ospa, jackknife_se, scenarios  # noqa: E402

from gmjax import multitarget as mt  # noqa: E402

C_OSPA, P_OSPA = 100.0, 1.0
OSPA2_WINDOW = 10
GATE = 100.0
CAPACITY, MERGE_CAPACITY, N_MAX = 50, 200, 30
LMB_TRACKS, LMB_COMPONENTS, LMB_SAMPLES = 30, 5, 500
BURN_IN = 5
FILTERS = ("phd", "cphd", "lmb")
ESTIMATORS = {
    "phd_mass": "PHD mass (sum w)",
    "phd_count": "PHD count (Table III)",
    "cphd_mean": "CPHD mean",
    "cphd_map": "CPHD MAP count",
    "lmb_mean": "LMB sum r",
    "lmb_map": "LMB MAP count",
}
PAIRS = (
    ("lmb_mean", "cphd_mean"),
    ("lmb_mean", "phd_mass"),
    ("lmb_map", "cphd_map"),
    ("lmb_map", "phd_count"),
)


# ----------------------------------------------------------------------------- statistics


def cardinality_stats(estimates: dict[str, np.ndarray], truth: np.ndarray) -> dict:
    """Across-run variance (averaged over steps), bias and MSE of each ``(N, T)`` estimate, with standard
    errors, and the paired variance differences of :data:`PAIRS` (jackknife over runs)."""
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


def _summary(x: np.ndarray) -> dict:
    m, se = _mean_se(np.asarray(x, np.float64))
    return {"mean": m, "se": se, "z": m / se if se > 0 else float("nan")}


# ----------------------------------------------------------------------------- the study


def _slim(infos, dims: tuple[int, ...]) -> dict:
    """What the study reads from a filter's ``(N, T)`` infos (keeps the program's output small)."""
    ex = infos.extra
    out = {
        "cardinality": ex["cardinality"],
        "n_estimates": ex["n_estimates"],
        "estimates": jnp.take(ex["estimates"], jnp.asarray(dims), axis=-1),
        "estimate_mask": ex["estimate_mask"],
        "overflow": infos.flags.overflow,
        "degenerate": infos.flags.degenerate,
        "repaired": infos.flags.repaired,
    }
    if infos.reduction is not None:
        out["reducer_overflow"] = infos.reduction.overflow  # Vo-Ma kept its J_max heaviest components
    for k in ("cardinality_variance", "estimate_labels", "n_hypotheses", "n_tracks"):
        if k in ex:
            out[k] = ex[k]
    return out


def _track_metrics(truth, alive, est, labels, mask, start: int) -> dict:
    """OSPA^(2) (per run: mean over steps ``start + 1 .. T``), label switches and fragmentations (per run,
    every scan) of the LMB's labelled estimates; host-side, one run at a time."""
    n_runs = truth.shape[0]
    ospa2 = np.zeros(truth.shape[:2])
    switches = np.zeros(n_runs, np.int64)
    frags = np.zeros(n_runs, np.int64)
    for i in range(n_runs):
        args = (truth[i], alive[i], est[i], labels[i], mask[i])
        ospa2[i] = mt.tracks.ospa2(
            *args, cutoff=C_OSPA, order=P_OSPA, window=OSPA2_WINDOW, position_dims=(0, 1)
        )
        ls = mt.tracks.label_switches(*args, gate=GATE, position_dims=(0, 1))
        switches[i] = ls.total
        frags[i] = int(ls.fragmentations.sum())
    return {"ospa2": ospa2, "switches": switches, "fragmentations": frags}


def run_study(
    sc: mt.MultiTargetScenario,
    *,
    runs: int,
    seed: int = 0,
    samples: int = LMB_SAMPLES,
    tracks: int = LMB_TRACKS,
    components: int = LMB_COMPONENTS,
    repeats: int = 1,
    burn_in: int = BURN_IN,
) -> dict:
    """Simulate ``runs`` runs of ``sc``, filter them with the GM-PHD, GM-CPHD and GM-LMB and score them.

    Returns:
        A JSON-able dict: settings, ``timing`` per filter, ``cardinality`` (:func:`cardinality_stats`),
        ``ospa`` (per filter and paired differences), ``lmb_tracks`` (OSPA^(2), label switches,
        fragmentations, hypotheses), flags, and per-step series for the plot.
    """
    T = int(sc.n_steps)
    start = min(int(burn_in), T - 1)
    dims = tuple(int(i) for i in sc.position_dims)
    sim_key, filter_key = jax.random.split(jax.random.PRNGKey(seed))
    samples_ = jax.jit(jax.vmap(lambda k: mt.simulate(sc, k)))(jax.random.split(sim_key, runs))
    block(samples_)
    run_keys = jax.random.split(filter_key, runs)  # the LMB's Gibbs sampler: one key per run
    kw = dict(capacity=CAPACITY, merge_capacity=MERGE_CAPACITY)
    filters = {
        "phd": mt.gm_phd(sc.model, **sc.filter_kwargs(), **kw),
        "cphd": mt.gm_cphd(sc.model, **sc.filter_kwargs(), n_max=N_MAX, **kw),
        "lmb": mt.gm_lmb(
            sc.model,
            **sc.filter_kwargs(),
            capacity=tracks,
            components_per_track=components,
            n_samples=samples,
        ),
    }
    args = {"phd": (samples_.zs,), "cphd": (samples_.zs,), "lmb": (samples_.zs, run_keys)}
    compiled, timing = {}, {}
    for name, f in filters.items():
        if name == "lmb":
            prog = jax.jit(jax.vmap(lambda z, k, f=f: _slim(mt.run(f, z, key=k)[1], dims)))
        else:
            prog = jax.jit(jax.vmap(lambda z, f=f: _slim(mt.run(f, z)[1], dims)))
        t0 = time.perf_counter()
        compiled[name] = prog.lower(*args[name]).compile()
        timing[name] = {"compile_s": time.perf_counter() - t0, "runs_s": []}
        print(f"  compiled {name} in {timing[name]['compile_s']:.1f} s", flush=True)
    outs = {}
    for _ in range(max(1, repeats)):  # alternate the filters: a slow spell slows all alike
        for name, prog in compiled.items():
            t0 = time.perf_counter()
            outs[name] = block(prog(*args[name]))
            timing[name]["runs_s"].append(time.perf_counter() - t0)
            print(f"  ran {name} in {timing[name]['runs_s'][-1]:.1f} s", flush=True)
    for tm in timing.values():
        tm["run_median_s"] = float(np.median(tm["runs_s"]))
        tm["run_min_s"] = float(np.min(tm["runs_s"]))
        tm["us_per_run_scan"] = 1e6 * tm["run_median_s"] / (runs * T)
    outs = {k: {n: np.asarray(a) for n, a in v.items()} for k, v in outs.items()}

    states = np.asarray(samples_.states)[..., list(dims)]  # (N, T, n, 2) true positions
    alive = np.asarray(samples_.alive)
    truth = alive.sum(-1).astype(np.float64)  # (N, T)
    raw = {
        "phd_mass": outs["phd"]["cardinality"],
        "phd_count": outs["phd"]["n_estimates"],
        "cphd_mean": outs["cphd"]["cardinality"],
        "cphd_map": outs["cphd"]["n_estimates"],
        "lmb_mean": outs["lmb"]["cardinality"],
        "lmb_map": outs["lmb"]["n_estimates"],
    }
    window = {k: np.asarray(v, np.float64)[:, start:] for k, v in raw.items()}
    card = cardinality_stats(window, truth[:, start:])
    card["phd_mass"]["reported_var"] = float(window["phd_mass"].mean())  # Poisson: variance = mean
    for k in ("cphd", "lmb"):
        card[f"{k}_mean"]["reported_var"] = float(outs[k]["cardinality_variance"][:, start:].mean())

    ospa = {k: _ospa(outs[k]["estimates"], outs[k]["estimate_mask"], states, alive) for k in FILTERS}
    per_run = {k: v[:, start:].mean(1) for k, v in ospa.items()}
    ospa_summary = {k: _summary(v) for k, v in per_run.items()}
    for a, b in (("lmb", "cphd"), ("lmb", "phd"), ("cphd", "phd")):
        ospa_summary[f"{a}-{b}"] = _summary(per_run[a] - per_run[b])

    t0 = time.perf_counter()
    trk = _track_metrics(
        states,
        alive,
        outs["lmb"]["estimates"],
        outs["lmb"]["estimate_labels"],
        outs["lmb"]["estimate_mask"],
        start,
    )
    track_s = time.perf_counter() - t0
    o2_run = trk["ospa2"][:, start:].mean(1)
    hyp = outs["lmb"]["n_hypotheses"][:, start:].astype(np.float64)
    lmb_tracks = {
        "ospa2": _summary(o2_run),
        "ospa2-ospa": _summary(o2_run - per_run["lmb"]),
        "switches": {**_summary(trk["switches"]), "total": int(trk["switches"].sum())},
        "fragmentations": {**_summary(trk["fragmentations"]), "total": int(trk["fragmentations"].sum())},
        "hypotheses_mean": float(hyp.mean()),
        "hypotheses_max": int(hyp.max()),
        "hypotheses_at_budget_steps": int((hyp >= samples).sum()),
        "n_tracks_mean": float(outs["lmb"]["n_tracks"][:, start:].mean()),
        "n_tracks_max": int(outs["lmb"]["n_tracks"].max()),
        "host_metrics_s": track_s,
    }

    series = {
        "true_cardinality": truth[0].tolist(),
        **{f"{k}_mean": np.asarray(v, np.float64).mean(0).tolist() for k, v in raw.items()},
        **{
            f"{k}_sd": (np.asarray(v, np.float64).std(0, ddof=1) if runs > 1 else np.zeros(T)).tolist()
            for k, v in raw.items()
        },
        **{f"ospa_{k}": v.mean(0).tolist() for k, v in ospa.items()},
        "ospa2_lmb": trk["ospa2"].mean(0).tolist(),
        "hypotheses_lmb": outs["lmb"]["n_hypotheses"].mean(0).tolist(),
    }
    flags = {}
    for k in FILTERS:
        for flag in ("overflow", "reducer_overflow", "degenerate", "repaired"):
            if flag in outs[k]:
                flags[f"{k}_{flag}_steps"] = int(outs[k][flag].sum())
    flags["scan_overflow_steps"] = int(np.asarray(samples_.overflow).sum())
    bw = np.asarray(sc.birth.weights)[np.asarray(sc.birth.mask)]
    return {
        "scenario": sc.name,
        "runs": runs,
        "steps": T,
        "window": [start + 1, T],
        "seed": seed,
        "clutter_rate": float(sc.clutter_rate),
        "detection_prob": float(sc.detection_prob),
        "survival_prob": float(sc.survival_prob),
        "max_measurements": int(sc.max_measurements),
        "n_targets": sc.n_targets,
        "position_dims": list(dims),
        "birth_weights": bw.tolist(),
        "max_true_cardinality": int(truth.max()),
        "n_max": N_MAX,
        "capacity": CAPACITY,
        "merge_capacity": MERGE_CAPACITY,
        "lmb_tracks_capacity": tracks,
        "lmb_components": components,
        "lmb_samples": samples,
        "timing": timing,
        "cardinality": card,
        "ospa": ospa_summary,
        "lmb_tracks": lmb_tracks,
        "flags": flags,
        "series": series,
    }


# ----------------------------------------------------------------------------- report


def _pm(v: float, se: float, digits: int = 4) -> str:
    return f"{v:.{digits}f} ± {se:.{digits}f}"


def _cmp(d: float, se: float, digits: int = 4) -> str:
    """``d ± se (z s.e.)`` and a word: below/above by more than 3 s.e., or not separated."""
    if not np.isfinite(se) or se <= 0:
        return f"{d:+.{digits}f} (no standard error)"
    z = d / se
    word = "lower by > 3 s.e." if z < -3 else "higher by > 3 s.e." if z > 3 else "not separated by 3 s.e."
    return f"{d:+.{digits}f} ± {se:.{digits}f} ({z:+.1f} s.e., {word})"


def verdict(res: dict) -> str:
    """Checked, not assumed: the LMB's cardinality variance and OSPA against the CPHD's and the PHD's."""
    c, o = res["cardinality"], res["ospa"]
    parts = [
        f"{ESTIMATORS[a]} - {ESTIMATORS[b]} variance {_cmp(c[f'{a}-{b}']['var'], c[f'{a}-{b}']['var_se'])}"
        for a, b in PAIRS
    ]
    parts += [
        f"OSPA LMB - {b.upper()} {_cmp(o[f'lmb-{b}']['mean'], o[f'lmb-{b}']['se'], 3)} m"
        for b in ("cphd", "phd")
    ]
    return f"**{res['scenario']}** ({res['runs']} runs), checked, not assumed: " + "; ".join(parts) + "."


def _flag_text(fl: dict) -> str:
    parts = []
    for k in FILTERS:
        bits = [f"overflow {fl[f'{k}_overflow_steps']}"]
        if f"{k}_reducer_overflow_steps" in fl:
            bits[0] += f" (reducer's J_max cap: {fl[f'{k}_reducer_overflow_steps']})"
        bits += [f"degenerate {fl[f'{k}_degenerate_steps']}", f"repaired {fl[f'{k}_repaired_steps']}"]
        parts.append(f"{k.upper()} " + ", ".join(bits))
    return "; ".join(parts) + f"; scans over capacity {fl['scan_overflow_steps']}"


def scenario_markdown(res: dict) -> list[str]:
    c, o, tm, lt = res["cardinality"], res["ospa"], res["timing"], res["lmb_tracks"]
    bw = ", ".join(f"{w:g}" for w in res["birth_weights"])
    md = [
        f"## {res['scenario']}",
        "",
        f"{res['runs']} runs x {res['steps']} steps (statistics over steps {res['window'][0]}..{res['window'][1]}), "
        f"clutter {res['clutter_rate']:g}/scan, P_D = {res['detection_prob']:g}, P_S = {res['survival_prob']:g}, "
        f"M = {res['max_measurements']}, {res['n_targets']} targets (at most {res['max_true_cardinality']} alive). "
        f"PHD/CPHD: J = {res['capacity']}, merge capacity {res['merge_capacity']}, N_max = {res['n_max']}. "
        f"LMB: T = {res['lmb_tracks_capacity']} tracks, J = {res['lmb_components']} components per track, "
        f"G = {res['lmb_samples']} Gibbs rows.",
        "",
        f"Birth weights (`sc.birth.weights`, {len(res['birth_weights'])} sites): {bw}. The PHD/CPHD read them as "
        "expected births per step per site; the LMB, unchanged, as each birth track's existence probability "
        f"(a birth track per site per step, {sum(res['birth_weights']):g} expected births per step in both).",
        "",
    ]
    rows = [
        [
            label,
            _pm(c[k]["var"], c[k]["var_se"]),
            f"{c[k]['reported_var']:.4f}" if "reported_var" in c[k] else "-",
            _pm(c[k]["bias"], c[k]["bias_se"]),
            _pm(c[k]["mse"], c[k]["mse_se"]),
        ]
        for k, label in ESTIMATORS.items()
    ]
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
            ["pair", "variance difference", "in s.e."],
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
            ["filter", "mean OSPA (m)", "compile s", "run s (median)", "µs per run-scan"],
            [
                [
                    name.upper(),
                    _pm(o[name]["mean"], o[name]["se"], 3),
                    f"{tm[name]['compile_s']:.2f}",
                    f"{tm[name]['run_median_s']:.2f}",
                    f"{tm[name]['us_per_run_scan']:.0f}",
                ]
                for name in FILTERS
            ],
        )
    )
    md += ["", f"OSPA (c = {C_OSPA:g} m, p = {P_OSPA:g}) paired differences (s.e. over runs):", ""]
    md.append(
        markdown_table(
            ["pair", "OSPA difference (m)", "in s.e."],
            [
                [
                    f"{a.upper()} - {b.upper()}",
                    _pm(o[f"{a}-{b}"]["mean"], o[f"{a}-{b}"]["se"], 3),
                    f"{o[f'{a}-{b}']['z']:+.1f}",
                ]
                for a, b in (("lmb", "cphd"), ("lmb", "phd"), ("cphd", "phd"))
            ],
        )
    )
    sw, fr = lt["switches"], lt["fragmentations"]
    md += ["", "LMB track metrics (labelled estimates):", ""]
    md.append(
        markdown_table(
            ["metric", "value"],
            [
                [
                    f"OSPA^(2) (c = {C_OSPA:g} m, p = {P_OSPA:g}, window {OSPA2_WINDOW}), mean over steps and runs",
                    _pm(lt["ospa2"]["mean"], lt["ospa2"]["se"], 3) + " m",
                ],
                [
                    "OSPA^(2) - OSPA (per run, paired)",
                    _pm(lt["ospa2-ospa"]["mean"], lt["ospa2-ospa"]["se"], 3) + " m",
                ],
                [
                    f"label switches per run (gate {GATE:g} m, every scan)",
                    f"{_pm(sw['mean'], sw['se'], 3)} (total {sw['total']})",
                ],
                ["fragmentations per run", f"{_pm(fr['mean'], fr['se'], 3)} (total {fr['total']})"],
                [
                    "distinct hypotheses per update (mean / max)",
                    f"{lt['hypotheses_mean']:.1f} / {lt['hypotheses_max']} of G = {res['lmb_samples']} "
                    f"(steps at the budget: {lt['hypotheses_at_budget_steps']})",
                ],
                [
                    "live tracks after the update (mean / max)",
                    f"{lt['n_tracks_mean']:.2f} / {lt['n_tracks_max']}",
                ],
            ],
        )
    )
    r_cphd = tm["lmb"]["us_per_run_scan"] / tm["cphd"]["us_per_run_scan"]
    r_phd = tm["lmb"]["us_per_run_scan"] / tm["phd"]["us_per_run_scan"]
    md += [
        "",
        f"LMB / CPHD time per run-scan: {r_cphd:.2f}x; LMB / PHD: {r_phd:.2f}x. Flags (steps of all runs): "
        f"{_flag_text(res['flags'])}.",
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
            f"{s['lmb_mean_mean'][k]:.3f} ± {s['lmb_mean_sd'][k]:.3f}",
            f"{s['ospa_phd'][k]:.2f}",
            f"{s['ospa_cphd'][k]:.2f}",
            f"{s['ospa_lmb'][k]:.2f}",
            f"{s['ospa2_lmb'][k]:.2f}",
        ]
        for k in range(0, T, max(1, T // 10))
    ]
    md.append(
        markdown_table(
            [
                "step",
                "true n",
                "PHD mass (mean ± sd)",
                "CPHD mean (mean ± sd)",
                "LMB sum r (mean ± sd)",
                "OSPA PHD",
                "OSPA CPHD",
                "OSPA LMB",
                "OSPA^(2) LMB",
            ],
            trow,
        )
    )
    return md + [""]


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    fig, axes = plt.subplots(2, len(names), figsize=(6 * len(names), 6.5), squeeze=False)
    curves = (
        ("phd", "phd_mass", "C0", "PHD mass"),
        ("cphd", "cphd_mean", "C3", "CPHD mean"),
        ("lmb", "lmb_mean", "C2", "LMB sum r"),
    )
    for j, name in enumerate(names):
        s = results[name]["series"]
        steps = np.arange(1, len(s["true_cardinality"]) + 1)
        ax = axes[0, j]
        ax.step(steps, s["true_cardinality"], "k", where="mid", lw=1.2, label="truth")
        for _, key, color, label in curves:
            m, sd = np.asarray(s[f"{key}_mean"]), np.asarray(s[f"{key}_sd"])
            ax.plot(steps, m, color=color, lw=1, label=f"{label} ± sd")
            ax.fill_between(steps, m - sd, m + sd, color=color, alpha=0.15, lw=0)
        ax.set(xlabel="step", ylabel="cardinality", title=f"{name} ({results[name]['runs']} runs)")
        ax.legend(fontsize=8)
        ax = axes[1, j]
        for k, _, color, _ in curves:
            ax.plot(steps, s[f"ospa_{k}"], color=color, lw=1, label=f"OSPA {k.upper()}")
        ax.plot(steps, s["ospa2_lmb"], "C2--", lw=1, label=f"OSPA^(2) LMB (window {OSPA2_WINDOW})")
        ax.set(xlabel="step", ylabel=f"mean over runs (m), c = {C_OSPA:g}, p = {P_OSPA:g}")
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
    parser.add_argument(
        "--samples", type=int, default=LMB_SAMPLES, help="the LMB's Gibbs rows per update (G)"
    )
    parser.add_argument("--tracks", type=int, default=LMB_TRACKS, help="the LMB's track slots (T)")
    parser.add_argument("--repeats", type=int, default=1, help="timed calls of each compiled filter")
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
            samples=args.samples,
            tracks=args.tracks,
            repeats=args.repeats,
            burn_in=args.burn_in,
        )
        tm = results[name]["timing"]
        print(
            "  " + ", ".join(f"{k.upper()} {tm[k]['us_per_run_scan']:.0f} µs/run-scan" for k in FILTERS),
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
            "n_max": N_MAX,
            "capacity": CAPACITY,
            "merge_capacity": MERGE_CAPACITY,
            "reducer": "VoMa(1e-5, 4.0, max_components=capacity) (the PHD/CPHD default)",
            "lmb": {
                "capacity": args.tracks,
                "components_per_track": LMB_COMPONENTS,
                "n_samples": args.samples,
                "existence_threshold": 1e-3,
                "component_threshold": 1e-5,
            },
            "ospa": {"c": C_OSPA, "p": P_OSPA},
            "ospa2": {"c": C_OSPA, "p": P_OSPA, "window": OSPA2_WINDOW},
            "label_switch_gate": GATE,
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
        "# GM-PHD vs GM-CPHD vs GM-LMB: cardinality, OSPA, track metrics and speed (issue 47, item 5)",
        "",
        f"Machine load (1/5/15-min averages, {os.cpu_count()} cores) before {tuple(round(x, 2) for x in load_before)}, "
        f"after {tuple(round(x, 2) for x in load_after)}: timings were taken on a shared, loaded CPU machine; "
        "compare ratios, not absolute seconds.",
        "",
        "All three filters run on the same simulated measurement sets, each one jitted program vmapped over the "
        "runs (compile time apart; the timed calls alternate the filters). PHD/CPHD: the Vo–Ma reducer "
        f"(T = 1e-5, U = 4), J = {CAPACITY}, {MERGE_CAPACITY} components to the reducer, CPHD N_max = {N_MAX}. "
        f"LMB: T = {args.tracks} track slots, J = {LMB_COMPONENTS} components per track, G = {args.samples} Gibbs "
        "rows per update, existence threshold 1e-3, component threshold 1e-5, one PRNG key per run. "
        "Cardinality estimates: the PHD's mass and Table III count, the CPHD's mean and MAP count, the LMB's "
        "sum r and MAP count (Poisson binomial of the r's). 'Variance across runs' is the per-step variance over "
        "runs (the true tracks are deterministic) averaged over the steps, ± a jackknife s.e. over runs; bias and "
        "MSE ± s.e. over runs. Reported variances: PHD Poisson (= mass), CPHD its cardinality pmf's, LMB "
        "sum r (1 - r). OSPA: per-scan sets, c = 100 m, p = 1; OSPA^(2) and label switches use the LMB's labels.",
        "",
    ]
    if args.note:
        md += [f"Note: {args.note}", ""]
    for res in results.values():
        md += scenario_markdown(res)
    md += ["## Summary", ""]
    for res in results.values():
        md += [verdict(res), ""]
    stem = "lmb_quick" if q else "lmb"
    png = RESULTS_DIR / f"{stem}.png"
    try:
        RESULTS_DIR.mkdir(parents=True, exist_ok=True)
        plot(results, png)
        md += [f"![cardinality, OSPA and OSPA^(2) over time]({png.name})", ""]
    except ImportError:
        md += ["(matplotlib is not installed: no plot.)", ""]
        print("matplotlib not installed: no plot")
    md += [f"Wall time {wall:.0f} s."]
    path = write_results("lmb", data, "\n".join(md), quick=q)
    print("\n".join(md))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
