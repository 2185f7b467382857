"""The compiled per-mixture loop as the speed limit for the expensive reducers (issue 46).

gmjax's batched reducers (``jax.jit(jax.vmap(reducer))``, as ``bench_reduction.py`` calls them:
Runnalls, West (KL) and GMRC) against the same reductions written as numba ``@njit`` per-mixture
loops with a ``prange`` batch driver (``references/reduction_numba.py``: cached log-determinants,
one cost row/column refreshed per merge — the strong baseline), on 1000 random mixtures of 60
components reduced to 20, d = 1, 2, 4, float64. PCM with the grid search of ``λ`` (seed 000;
``reduction.pcm(max_components=20, capacity=20, newton_steps=0)``, the 11-point grid on [1, 3])
against ``references/pcm_numba.py`` (the ``λ``-independent parts once per mixture, a grid point
with the previous one's judgment matrix or partition not costed again). Mixtures as seed 000's 30-component case
(w in [1e-2, 0.2] normalised, x in [-2, 4]^d, sigma in [0.4, 1] per axis of a random rotation).

Timing (``_common.time_alternating``): the first call of each program (compile + run) apart from
the steady calls, which run in alternating rounds in one process (gmjax, numba on all threads, numba
on one thread, gmjax, ...), so a slow spell of the machine slows all alike; median over the rounds.
Numba's compile time is its first call's time minus its median run (no on-disk cache). gmjax runs
the batch as a ``vmap`` over the mixtures, one core: each merge step (the selection by one
min-reduction of the cost matrices, the merge, one cost row/column) runs for every mixture at once;
numba's ``prange`` uses every core (``numba.get_num_threads()``), so the one-thread column is the
per-core comparison. The outputs are checked equal (max abs difference of weights, means,
covariances; same merge sequence / k-means iteration count; PCM: same labels and ``λ*``, except
*ties*: grid points whose clusterings are the same partition under other head rows have the same
EISE but for the summation order; gmjax keeps the first within ``K eps`` of the minimum, as the loop
keeps the first, but until 620bbd7 its ``argmin`` picked among them by rounding; a tie counts as
equal when the partition, the EISE and the mixture up to slot order agree, and the ties are counted).

Where the time goes (Runnalls only; ``--no-decompose`` skips it): the fixed part (the initial cost
matrix, the copy out) and the cost of one merge step. numba: the batch reduced to 60 (no merge) and to
20, ``(t(20) - t(60)) / 40`` per merge. gmjax: a reduction to 60 has no merge step and XLA drops its
unused cost matrix, so the fixed part is ``runnalls._initial_costs`` timed alone plus ``t(60)``.

The GSF per run-step against the whole R-GSF as a numba loop: ``bench_gsf_numba.py``.

Usage: ``python benchmarks/bench_reducer_limit.py [--quick] [--batch 1000] [--repeats 3]
[--reducers pcm ...]`` (or ``gmjax bench reducer_limit``). Needs numba (``pip install -e .[bench]``).
With ``--reducers`` naming some of the reducers, the rows measured replace those of the same
reducer and d in ``results/reducer_limit.json`` and the other rows are kept (the run's date and load
recorded under ``partial_runs``); the Runnalls split (``--decompose``) is kept unless Runnalls runs.
"""

from __future__ import annotations

import argparse
import os
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
from _common import markdown_table, time_alternating, with_numba_threads, write_results  # noqa: E402

from gmjax import reduction as R  # noqa: E402
from gmjax.mixture import GaussianMixture  # noqa: E402
from references import pcm_numba as pn  # noqa: E402
from references import reduction_numba as rn  # noqa: E402

try:
    import numba
except ImportError:  # the benchmark says so in main()
    numba = None

K_IN = 60
NUM_OUT = 20


def draw(rng, B, K, d):
    """``B`` mixtures of ``K`` components (seed 000's 30-component ranges), vectorised."""
    w = rng.uniform(1e-2, 0.2, (B, K))
    w /= w.sum(1, keepdims=True)
    m = rng.uniform(-2.0, 4.0, (B, K, d))
    q, _ = np.linalg.qr(rng.normal(size=(B, K, d, d)))
    s2 = rng.uniform(0.4, 1.0, (B, K, d)) ** 2
    P = np.einsum("bkij,bkj,bklj->bkil", q, s2, q)
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    return w, m, P


# --reducers names -> row names
REDUCERS = {"runnalls": "runnalls", "west": "west (KL)", "gmrc": "gmrc", "pcm": "pcm (grid)"}


def _reducers(num_out):
    """name -> (gmjax per-mixture fn, numba batch call ``f(w, m, P)``)."""
    return {
        "runnalls": (lambda g: R.runnalls(g, num_out), lambda w, m, P: rn.runnalls_batch(w, m, P, num_out)),
        "west (KL)": (lambda g: R.west(g, num_out), lambda w, m, P: rn.west_batch(w, m, P, num_out)),
        "gmrc": (lambda g: R.gmrc(g, num_out), lambda w, m, P: rn.gmrc_batch(w, m, P, num_out)),
        "pcm (grid)": (
            lambda g: R.pcm(g, max_components=num_out, capacity=num_out, newton_steps=0),
            lambda w, m, P: pn.pcm_batch(w, m, P, num_out, num_out),
        ),
    }


def _by_lowest_slot(w, m, P, mask, labels):
    """One mixture's live output slots ordered by the lowest input slot of their cluster, and the
    labels renamed to that order (an output's layout with the choice of head rows taken out)."""
    slots = [p for p in np.flatnonzero(mask) if (labels == p).any()]
    order = sorted(slots, key=lambda p: int(np.flatnonzero(labels == p)[0]))
    rename = np.full(len(mask) + 1, -1)
    rename[order] = np.arange(len(order))
    return w[order], m[order], P[order], rename[labels]


def _check_pcm(out, info, r):
    """PCM: ``(max abs diff, same, ties)``. A mixture with another ``λ*`` is a tie when its EISE
    agrees to 1e-12 and its partition and mixture agree once the slots are ordered by their lowest
    input slot (the same partition found at two grid points under other head rows)."""
    got = [np.asarray(a) for a in (out.weights, out.means, out.covs, out.mask, info.labels)]
    lam = np.asarray(info.aux["lambda"])
    same = bool(np.abs(np.asarray(info.cost) - r[6]).max() <= 1e-12)
    diff, ties = 0.0, 0
    for b in range(lam.shape[0]):
        if lam[b] == r[5][b]:
            same &= bool((got[3][b] == r[3][b]).all() and (got[4][b] == r[4][b]).all())
            diff = max(diff, *(float(np.abs(got[k][b] - r[k][b]).max()) for k in range(3)))
            continue
        ties += 1
        ours = _by_lowest_slot(*(a[b] for a in r[:5]))
        theirs = _by_lowest_slot(*(a[b] for a in got))
        same &= ours[3].shape == theirs[3].shape and bool((ours[3] == theirs[3]).all())
        if same:
            diff = max(diff, *(float(np.abs(x - y).max()) for x, y in zip(ours[:3], theirs[:3])))
    return diff, same, ties


def _check(name, out, info, r):
    """Max abs output difference, whether the discrete results agree, and (PCM) the ties."""
    if name == "pcm (grid)":
        return _check_pcm(out, info, r)
    diff = max(
        float(np.abs(np.asarray(out.weights) - r[0]).max()),
        float(np.abs(np.asarray(out.means) - r[1]).max()),
        float(np.abs(np.asarray(out.covs) - r[2]).max()),
    )
    same = bool((np.asarray(out.mask) == r[3]).all() and (np.asarray(info.labels) == r[4]).all())
    if name == "gmrc":
        same &= bool((np.asarray(info.aux["iterations"]) == r[5]).all())
    else:
        same &= bool((np.asarray(info.aux["merges"]) == r[5]).all())
    return diff, same, 0


def run_case(name, jfn, nfn, w, m, P, repeats, threads):
    B = w.shape[0]
    gm = GaussianMixture(jnp.asarray(w), jnp.asarray(m), jnp.asarray(P), jnp.ones(w.shape, bool))
    kernel = jax.jit(jax.vmap(jfn))
    t_g, t_n, t_1 = time_alternating(
        [
            lambda: kernel(gm),
            with_numba_threads(threads, lambda: nfn(w, m, P)),
            with_numba_threads(1, lambda: nfn(w, m, P)),
        ],
        repeats=repeats,
    )
    out, info = kernel(gm)
    diff, same, ties = _check(name, out, info, nfn(w, m, P))
    us = 1e6 / B
    return {
        "gmjax_us": t_g["run_median_s"] * us,
        "gmjax_min_us": t_g["run_min_s"] * us,
        "numba_us": t_n["run_median_s"] * us,
        "numba_min_us": t_n["run_min_s"] * us,
        "numba_1t_us": t_1["run_median_s"] * us,
        "numba_1t_min_us": t_1["run_min_s"] * us,
        "ratio": t_g["run_median_s"] / t_n["run_median_s"],
        "ratio_1t": t_g["run_median_s"] / t_1["run_median_s"],
        "gmjax_compile_s": t_g["compile_s"],
        "numba_compile_s": t_n["compile_s"],
        "max_abs_diff": diff,
        "same_discrete": same,
        "ties": ties,
    }


def decompose(w, m, P, repeats, threads):
    """Runnalls' fixed cost and cost per merge step.

    numba: the batch reduced to 60 (no merge: the cost matrix, the copy out) and to 20. gmjax: a
    reduction to 60 has no merge step, so XLA drops the unused cost matrix from that program; its
    fixed part is timed as the initial cost matrix (``runnalls._initial_costs``, what the loop
    starts from) plus the reduction to 60 (the copy out)."""
    import importlib

    runnalls_module = importlib.import_module("gmjax.reduction.runnalls")  # the package binds the function

    B = w.shape[0]
    gm = GaussianMixture(jnp.asarray(w), jnp.asarray(m), jnp.asarray(P), jnp.ones(w.shape, bool))
    rows = {}
    for n_out in (K_IN, 40, NUM_OUT):
        kernel = jax.jit(jax.vmap(lambda g, n_out=n_out: R.runnalls(g, n_out)))
        t_g, t_1 = time_alternating(
            [lambda: kernel(gm), with_numba_threads(1, lambda: rn.runnalls_batch(w, m, P, n_out))],
            repeats=repeats,
        )
        rows[n_out] = (t_g["run_median_s"] * 1e6 / B, t_1["run_median_s"] * 1e6 / B)
    costs = jax.jit(jax.vmap(runnalls_module._initial_costs))
    (t_c,) = time_alternating([lambda: costs(gm)], repeats=repeats)
    gmjax_fixed = t_c["run_median_s"] * 1e6 / B + rows[K_IN][0]
    n_merges = K_IN - NUM_OUT
    return {
        "us_per_mixture": {str(k): {"gmjax": v[0], "numba_1t": v[1]} for k, v in rows.items()},
        "gmjax_cost_matrix_us": t_c["run_median_s"] * 1e6 / B,
        "gmjax_fixed_us": gmjax_fixed,
        "gmjax_us_per_merge": (rows[NUM_OUT][0] - gmjax_fixed) / n_merges,
        "numba_1t_fixed_us": rows[K_IN][1],
        "numba_1t_us_per_merge": (rows[NUM_OUT][1] - rows[K_IN][1]) / n_merges,
    }


def _load_note(load0, cpu_count):
    # the load averages before the run (the run itself loads a core): the 1-minute one, or the
    # 5-minute one when other work has just paused
    loaded = max(float(load0[0]), float(load0[1])) > 0.75 * cpu_count
    return (
        "The machine was loaded before the run (other work on the same cores, or its load average "
        "still decaying after it), so compare the ratios (measured in alternating rounds in one "
        "process) rather than absolute times."
        if loaded
        else "The machine was otherwise quiet."
    )


def render(data):
    load0, load1 = data["loadavg_before"], data["loadavg_after"]
    th = data["numba_threads"]
    load_note = _load_note(load0, data["cpu_count"])
    md = [
        f"# Compiled per-mixture loops (numba) vs gmjax's batched reducers, {data['batch']} mixtures "
        f"{K_IN} -> {NUM_OUT}, float64",
        "",
        f"Measured {data['date']} on a {data['cpu_count']}-core CPU machine"
        f"{' (quick smoke run)' if data['quick'] else ''}, load average {' '.join(load0)} before and "
        f"{' '.join(load1)} after. {load_note} "
        f"Median of {data['repeats']} rounds; compile time apart. numba {data['numba_version']}, "
        f"jax {jax.__version__}. gmjax runs the batch as one `vmap` over the mixtures (one core); the numba "
        f"batch driver's `prange` used {th} threads ({data['numba_threading_layer']} threading layer), "
        "and the `1 thread` columns are the per-core comparison.",
        "",
    ]
    for run in data.get("partial_runs", []):
        md += [
            f"Rows of {', '.join(run['reducers'])} (d = {', '.join(str(d) for d in run['dims'])}) measured "
            f"separately, {run['date']}: {run['batch']} mixtures, load average {' '.join(run['loadavg_before'])} "
            f"before and {' '.join(run['loadavg_after'])} after. {_load_note(run['loadavg_before'], data['cpu_count'])} "
            f"Median of {run['repeats']} rounds; numba `prange` on {run['numba_threads']} threads.",
            "",
        ]
    header = [
        "d",
        "reducer",
        "gmjax µs/mixture",
        f"numba µs/mixture ({th} threads)",
        "numba µs/mixture (1 thread)",
        f"gmjax / numba ({th} thr)",
        "gmjax / numba (1 thr)",
        "gmjax compile s",
        "numba compile s",
        "max abs diff",
        "same merges",
    ]
    rows = []
    for r in data["rows"]:
        rows.append(
            [
                r["d"],
                r["reducer"],
                r["gmjax_us"],
                r["numba_us"],
                r["numba_1t_us"],
                r["ratio"],
                r["ratio_1t"],
                r["gmjax_compile_s"],
                r["numba_compile_s"],
                f"{r['max_abs_diff']:.1e}",
                f"{r['same_discrete']} ({r['ties']} ties)" if r.get("ties") else r["same_discrete"],
            ]
        )
    md += [markdown_table(header, rows), ""]
    md += [
        "The 1-thread columns compare one core with one core. numba compile time: the first call of that reducer's batch driver (every reducer's driver "
        "compiles its own copy of the shared helpers; a d that reuses an already compiled signature "
        "shows ~0). `same merges`: identical output masks, labels and merge sequence (GMRC: k-means "
        "iteration count; PCM: labels and the chosen λ). PCM (grid) is `reduction.pcm(max_components=20, "
        "capacity=20, newton_steps=0)` (11-point grid of λ on [1, 3], CI merge) against "
        "`references/pcm_numba.py`; a PCM *tie* is a mixture where two grid points give the same partition "
        "under other head rows (so another output order) with the same EISE but for the summation order, "
        "and gmjax picks another grid point than the loop (both keep the first, gmjax within K eps of the "
        "minimum; until 620bbd7 its `argmin` picked by rounding): counted equal when the partition, the "
        "EISE (to 1e-12) and the mixture up to slot order agree.",
        "",
    ]
    if data.get("decompose"):
        dec_rows = []
        for d, v in data["decompose"].items():
            dec_rows.append(
                [
                    d,
                    v.get("gmjax_cost_matrix_us", float("nan")),
                    v["gmjax_fixed_us"],
                    v["gmjax_us_per_merge"],
                    v["numba_1t_fixed_us"],
                    v["numba_1t_us_per_merge"],
                    v["gmjax_us_per_merge"] / v["numba_1t_us_per_merge"],
                ]
            )
        md += [
            "## Where gmjax's Runnalls time goes",
            "",
            f"The fixed part (the initial cost matrix, the copy out) and the cost of one merge step "
            "(selection, merge, one cost row/column), µs per mixture; numba on one thread. numba: the batch "
            f"reduced to {K_IN} (no merge) and to {NUM_OUT}, per merge (t({NUM_OUT}) - t({K_IN})) / "
            f"{K_IN - NUM_OUT}. gmjax: a reduction to {K_IN} has no merge step and XLA drops its unused cost "
            "matrix, so the fixed part is the initial cost matrix (`runnalls._initial_costs`, timed alone) "
            f"plus the reduction to {K_IN}, per merge (t({NUM_OUT}) - fixed) / {K_IN - NUM_OUT}. (Until "
            f"2026-12-07 gmjax's fixed part was t({K_IN}) alone: it missed the cost matrix and counted its "
            "time in the merge steps.) gmjax evaluates all K x K pair costs (both triangles: one broadcast "
            "kernel), numba the upper triangle.",
            "",
            markdown_table(
                [
                    "d",
                    "gmjax cost matrix µs",
                    "gmjax fixed µs",
                    "gmjax µs / merge",
                    "numba fixed µs",
                    "numba µs / merge",
                    "gmjax / numba per merge",
                ],
                dec_rows,
            ),
            "",
        ]
    md += [
        "The R-GSF per run-step against the whole R-GSF as a numba loop (EKF components and this Runnalls "
        "loop): `results/gsf_numba.md` (`bench_gsf_numba.py`).",
    ]
    return "\n".join(md)


def _merge_into_previous(data, names, dims, quick):
    """A run of some reducers: its rows replace those of the same (d, reducer) in the previous
    results file, whose other rows, header data and Runnalls split are kept; the run is recorded
    in ``partial_runs``. Without a previous file the run's own data is returned."""
    import json

    from _common import RESULTS_DIR

    path = RESULTS_DIR / f"reducer_limit{'_quick' if quick else ''}.json"
    if not path.exists():
        return data
    old = json.loads(path.read_text())
    for key in ("benchmark", "machine"):
        old.pop(key, None)  # write_results sets them again
    new_keys = {(r["d"], r["reducer"]) for r in data["rows"]}
    order = list(REDUCERS.values())
    rows = [r for r in old["rows"] if (r["d"], r["reducer"]) not in new_keys] + data["rows"]
    old["rows"] = sorted(rows, key=lambda r: (r["d"], order.index(r["reducer"])))
    if data["decompose"]:
        old["decompose"] = data["decompose"]
    run = {
        k: data[k] for k in ("date", "batch", "repeats", "numba_threads", "loadavg_before", "loadavg_after")
    }
    run.update(reducers=names, dims=dims, wall_s=data["wall_s"])
    old["partial_runs"] = [
        p
        for p in old.get("partial_runs", [])
        if not (set(p["reducers"]) <= set(names) and set(p["dims"]) <= set(dims))
    ] + [run]
    return old


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small smoke configuration")
    p.add_argument("--batch", type=int, default=None, help="mixtures per case (default 1000)")
    p.add_argument("--repeats", type=int, default=5, help="alternating timing rounds")
    p.add_argument("--dims", type=int, nargs="+", default=None, help="dimensions (default 1 2 4)")
    p.add_argument("--no-decompose", action="store_true", help="skip the fixed / per-merge split")
    p.add_argument("--render", action="store_true", help="rewrite reducer_limit.md from reducer_limit.json")
    p.add_argument(
        "--reducers",
        nargs="+",
        choices=sorted(REDUCERS),
        default=None,
        help="run only these (default all); their rows replace those in results/reducer_limit.json",
    )
    args = p.parse_args(argv)
    if args.render:
        import json

        from _common import RESULTS_DIR

        data = json.loads((RESULTS_DIR / "reducer_limit.json").read_text())
        (RESULTS_DIR / "reducer_limit.md").write_text(render(data).rstrip() + "\n")
        print(render(data))
        return data
    if numba is None or not rn.HAVE_NUMBA:
        raise SystemExit("bench_reducer_limit needs numba: pip install numba (or pip install -e .[bench])")
    B = args.batch or (50 if args.quick else 1000)
    dims = args.dims or ([2] if args.quick else [1, 2, 4])
    names = [REDUCERS[k] for k in REDUCERS if args.reducers is None or k in args.reducers]
    threads = numba.get_num_threads()
    date = subprocess.run(["date"], capture_output=True, text=True).stdout.strip()
    with open("/proc/loadavg") as f:
        load_before = f.read().split()[:3]
    rng = np.random.default_rng(46)
    rows, dec = [], {}
    t0 = time.perf_counter()
    for d in dims:
        w, m, P = draw(rng, B, K_IN, d)
        for name, (jfn, nfn) in _reducers(NUM_OUT).items():
            if name not in names:
                continue
            r = {"d": d, "reducer": name, **run_case(name, jfn, nfn, w, m, P, args.repeats, threads)}
            rows.append(r)
            print(
                f"d={d} {name}: gmjax {r['gmjax_us']:.1f} µs/mixture (compile {r['gmjax_compile_s']:.1f} s), "
                f"numba {r['numba_us']:.1f} ({threads} thr) / {r['numba_1t_us']:.1f} (1 thr) "
                f"(compile {r['numba_compile_s']:.1f} s), ratio {r['ratio']:.1f} / {r['ratio_1t']:.1f}, "
                f"max |diff| {r['max_abs_diff']:.1e}, same {r['same_discrete']}",
                flush=True,
            )
        if not args.no_decompose and "runnalls" in names:
            dec[str(d)] = decompose(w, m, P, args.repeats, threads)
            v = dec[str(d)]
            print(
                f"d={d} runnalls split: gmjax fixed {v['gmjax_fixed_us']:.1f} µs + {v['gmjax_us_per_merge']:.2f} "
                f"µs/merge; numba fixed {v['numba_1t_fixed_us']:.1f} + {v['numba_1t_us_per_merge']:.2f} µs/merge",
                flush=True,
            )
    with open("/proc/loadavg") as f:
        load_after = f.read().split()[:3]
    data = {
        "date": date,
        "batch": B,
        "k_in": K_IN,
        "num_out": NUM_OUT,
        "repeats": args.repeats,
        "quick": args.quick,
        "cpu_count": os.cpu_count(),
        "numba_version": numba.__version__,
        "numba_threads": threads,
        "numba_threading_layer": numba.threading_layer(),
        "loadavg_before": load_before,
        "loadavg_after": load_after,
        "wall_s": time.perf_counter() - t0,
        "rows": rows,
        "decompose": dec,
        "gsf_comparison": "not done",
    }
    if len(names) < len(REDUCERS):
        data = _merge_into_previous(data, names, dims, args.quick)
    md = render(data)
    path = write_results("reducer_limit", data, md, quick=args.quick)
    print(md)
    print(f"wrote {path}")
    return data


if __name__ == "__main__":
    main()
