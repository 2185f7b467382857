"""Static mixture-reduction comparison (seed 000 Sec. IV-B, Tables 5–6) and batched throughput.

For 1-D and 2-D random mixtures drawn with seed 000's ranges (30 components: w in [1e-2, 0.2],
x in [-2, 4], sigma in [0.4, 1], target 20; 100 components: w in [1e-3, 0.1], x in [-7, 6],
sigma in [0.3, 2], target 60; weights drawn uniformly in the range and then normalised to 1, as
the paper's "sum w_i = 1" requires), every reducer is run as one ``jit(vmap(...))`` kernel over
all draws; we report the mean and spread of ISE / NISE (seed 000 eqs 42–43), the final count, the
time per reduction (batched run time / draws) and the compile time apart. The batched Runnalls
throughput is compared with the plain NumPy per-mixture loops of ``references``, in
the same process. Seed 000's Table 5 / 6 figures (one random draw, MATLAB, i5-4590) are printed
beside ours.

Run: ``python benchmarks/bench_reduction.py [--quick] [--draws N]``.
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

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import markdown_table, time_jax, time_python, write_results  # noqa: E402

from gmjax import reduction as R  # noqa: E402
from gmjax.metrics import ise, nise  # noqa: E402
from gmjax.mixture import GaussianMixture  # noqa: E402
from references import reduction_np as ref  # noqa: E402

CASES = {
    30: {"w": (1e-2, 0.2), "x": (-2.0, 4.0), "s": (0.4, 1.0), "target": 20},
    100: {"w": (1e-3, 0.1), "x": (-7.0, 6.0), "s": (0.3, 2.0), "target": 60},
}

# seed 000 Table 5 (l = 30) and Table 6 (l = 100): ISE, NISE, CPU time (s), final number
PAPER = {
    30: {
        "NL-GMR (prune_top)": (7.1e-2, 2.5e-3, 2e-3, 15),
        "PCM-GMR": (2.5e-3, 8.8e-5, 1.1e-2, 13),
        "R-GMR (runnalls)": (3.4e-3, 1.2e-4, 2.5e-2, 15),
    },
    100: {
        "NL-GMR (prune_top)": (3.3e-2, 1.9e-3, 3e-3, 60),
        "PCM-GMR": (4.2e-4, 2.5e-5, 3.1e-2, 48),
        "R-GMR (runnalls)": (6.4e-3, 3.9e-4, 5.9e-2, 60),
    },
}


def draw(rng, n, d, case):
    """One mixture with seed 000's ranges (d > 1: random rotation of per-axis sigmas)."""
    w = rng.uniform(*case["w"], n)
    w = w / w.sum()
    m = rng.uniform(*case["x"], (n, d))
    if d == 1:
        P = rng.uniform(*case["s"], (n, 1, 1)) ** 2
    else:
        P = np.empty((n, d, d))
        for k in range(n):
            q, _ = np.linalg.qr(rng.normal(size=(d, d)))
            P[k] = q @ np.diag(rng.uniform(*case["s"], d) ** 2) @ q.T
            P[k] = 0.5 * (P[k] + P[k].T)
    return w, m, P


def stack(comps):
    w = np.stack([c[0] for c in comps])
    m = np.stack([c[1] for c in comps])
    P = np.stack([c[2] for c in comps])
    mask = np.ones(w.shape, bool)
    return GaussianMixture(jnp.asarray(w), jnp.asarray(m), jnp.asarray(P), jnp.asarray(mask))


def reducers(target, full):
    """name -> (fn(gm) -> (gm, info), max draws (None: all))."""
    out = {
        "prune_top (NL-GMR)": (lambda g: R.prune_top(g, target), None),
        "prune_censored (rho=.9544, N_u=target)": (lambda g: R.prune_censored(g, 0.9544, target), None),
        "runnalls (R-GMR)": (lambda g: R.runnalls(g, target), None),
        "west (KL)": (lambda g: R.west(g, target), None),
        "west (ISE)": (lambda g: R.west(g, target, metric="ise"), None),
        "salmond": (lambda g: R.salmond(g, target), None),
        "kmeans": (lambda g: R.kmeans(g, target), None),
        "gmrc": (lambda g: R.gmrc(g, target), None),
        "vo_ma (U=1, J_max=target)": (lambda g: R.vo_ma(g, 1e-5, 1.0, target), None),
    }
    if full:
        small = 20 if target == 20 else 3  # O(K^3) per step: a few draws only
        out.update(
            {
                "williams": (lambda g: R.williams(g, target), small),
                "cowa": (lambda g: R.cowa(g, target), small),
                "runnalls + ise_refine(100)": (
                    lambda g: R.ise_refine(
                        R.runnalls(g, target, capacity=target)[0], g, n_steps=100, learning_rate=0.01
                    ),
                    small,
                ),
            }
        )
    return out


@jax.jit
def _scores(g, out):
    return jax.vmap(ise)(g, out), jax.vmap(nise)(g, out)


def run_case(n, d, draws, full, rng, repeats):
    case = CASES[n]
    target = case["target"]
    comps = [draw(rng, n, d, case) for _ in range(draws)]
    gm = stack(comps)
    rows, data = [], {}
    for name, (fn, cap_draws) in reducers(target, full).items():
        nd = draws if cap_draws is None else min(draws, cap_draws)
        g = jax.tree_util.tree_map(lambda a: a[:nd], gm)

        kernel = jax.jit(jax.vmap(fn))  # the reduction alone is timed
        t = time_jax(kernel, g, repeats=repeats)
        out, info = kernel(g)
        e, ne = _scores(g, out)
        e, ne, cnt = np.asarray(e), np.asarray(ne), np.asarray(info.n_out)
        per = t["run_median_s"] / nd
        data[name] = {
            "draws": nd,
            "ise_mean": e.mean(),
            "ise_std": e.std(),
            "nise_mean": ne.mean(),
            "nise_std": ne.std(),
            "count_mean": cnt.mean(),
            "time_per_reduction_s": per,
            "compile_s": t["compile_s"],
            "batch_run_s": t["run_median_s"],
        }
        rows.append(
            [name, nd, e.mean(), e.std(), ne.mean(), ne.std(), float(cnt.mean()), per, t["compile_s"]]
        )
        print(f"  {n}/{d}-D {name}: {per:.3g} s/reduction, compile {t['compile_s']:.3g} s", flush=True)
    return rows, data, comps, gm


def throughput(comps, gm, target, n_np, repeats):
    """Batched Runnalls (one jit(vmap) call over all draws) vs the NumPy per-mixture loops."""
    kernel = jax.jit(jax.vmap(lambda g: R.runnalls(g, target)[0]))
    t = time_jax(kernel, gm, repeats=repeats)
    B = gm.weights.shape[0]
    jax_rate = B / t["run_median_s"]
    sub = comps[:n_np]
    t_naive = time_python(
        lambda: [ref.runnalls(w, m, P, target) for w, m, P in sub[: max(1, n_np // 5)]], repeats=1
    )
    naive_rate = max(1, n_np // 5) / t_naive["run_median_s"]
    t_cached = time_python(lambda: [ref.runnalls_cached(w, m, P, target) for w, m, P in sub], repeats=repeats)
    cached_rate = len(sub) / t_cached["run_median_s"]
    # same answer check on the timed mixtures
    out = kernel(jax.tree_util.tree_map(lambda a: a[: len(sub)], gm))
    r = ref.runnalls_cached(*sub[0], target)
    same = np.allclose(np.asarray(out.weights[0][:target]), r["w"], atol=1e-10)
    return {
        "batch": B,
        "jax_reductions_per_s": jax_rate,
        "jax_compile_s": t["compile_s"],
        "numpy_cached_reductions_per_s": cached_rate,
        "numpy_naive_reductions_per_s": naive_rate,
        "speedup_vs_cached": jax_rate / cached_rate,
        "speedup_vs_naive": jax_rate / naive_rate,
        "same_result": bool(same),
    }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small smoke configuration")
    p.add_argument("--draws", type=int, default=None, help="mixtures per case (default 1000)")
    args = p.parse_args(argv)
    draws = args.draws or (20 if args.quick else 1000)
    repeats = 2
    dims = (1,) if args.quick else (1, 2)
    rng = np.random.default_rng(2024)
    md = [
        f"# Mixture reduction benchmark ({'quick' if args.quick else 'full'}, {draws} draws per case)",
        "",
        "ISE / NISE: seed 000 eqs 42–43 against the unreduced mixture; time: batched "
        "jit(vmap) run time per reduction (compile apart).",
        "",
    ]
    results = {"draws": draws, "cases": {}, "paper": {str(k): v for k, v in PAPER.items()}}
    header = [
        "reducer",
        "draws",
        "ISE mean",
        "ISE std",
        "NISE mean",
        "NISE std",
        "final count",
        "s / reduction",
        "compile s",
    ]
    for d in dims:
        for n in (30, 100):
            t0 = time.perf_counter()
            rows, data, comps, gm = run_case(n, d, draws, not args.quick, rng, repeats)
            key = f"{d}d_{n}"
            results["cases"][key] = data
            md += [f"## {d}-D, {n} -> {CASES[n]['target']} components", "", markdown_table(header, rows), ""]
            if d == 1:
                md += [
                    f"Seed 000 Table {5 if n == 30 else 6} (one draw, MATLAB): ",
                    "",
                    markdown_table(
                        ["method", "ISE", "NISE", "CPU s", "final number"],
                        [[k, *v] for k, v in PAPER[n].items()],
                    ),
                    "",
                ]
            if n == 100:
                n_np = 10 if args.quick else 50
                tp = throughput(comps, gm, CASES[n]["target"], n_np, repeats)
                results["cases"][key]["throughput_runnalls"] = tp
                md += [
                    f"Batched Runnalls {n} -> {CASES[n]['target']} ({d}-D), {tp['batch']} "
                    "mixtures in one call:",
                    "",
                    markdown_table(
                        ["implementation", "reductions / s", "gmjax speed-up"],
                        [
                            ["gmjax jit(vmap)", tp["jax_reductions_per_s"], 1.0],
                            [
                                "NumPy loop, cached cost matrix",
                                tp["numpy_cached_reductions_per_s"],
                                tp["speedup_vs_cached"],
                            ],
                            [
                                "NumPy loop, recomputed costs (reference)",
                                tp["numpy_naive_reductions_per_s"],
                                tp["speedup_vs_naive"],
                            ],
                        ],
                    ),
                    "",
                    f"same result as NumPy: {tp['same_result']}",
                    "",
                ]
            print(f"case {key}: {time.perf_counter() - t0:.1f} s", flush=True)
    path = write_results("reduction", results, "\n".join(md), quick=args.quick)
    print("\n".join(md))
    print(f"wrote {path}")
    return results


if __name__ == "__main__":
    main()
