"""ISE between batches of 100-component 2-D mixture pairs: compiled gmjax vs NumPy in the same run.

Usage: python benchmarks/bench_metrics.py [--quick] [--pairs N]
Writes benchmarks/results/metrics.json and metrics.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # references/

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import markdown_table, time_jax, time_python, write_results  # noqa: E402

from gmjax import GaussianMixture, metrics  # noqa: E402
from references import metrics_np  # noqa: E402


def random_batch(rng, n_pairs, K, d=2):
    w = rng.uniform(1e-3, 0.1, (n_pairs, K))
    w /= w.sum(1, keepdims=True)
    m = rng.uniform(-7, 6, (n_pairs, K, d))
    s = rng.uniform(0.3, 2.0, (n_pairs, K, d))
    rho = rng.uniform(-0.5, 0.5, (n_pairs, K))
    P = np.zeros((n_pairs, K, d, d))
    P[..., 0, 0] = s[..., 0] ** 2
    P[..., 1, 1] = s[..., 1] ** 2
    P[..., 0, 1] = P[..., 1, 0] = rho * s[..., 0] * s[..., 1]
    return w, m, P


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small smoke run")
    parser.add_argument("--pairs", type=int, default=None, help="number of mixture pairs (default 1000)")
    parser.add_argument("--components", type=int, default=100)
    parser.add_argument("--numpy-pairs", type=int, default=None, help="pairs timed for the NumPy loop")
    args = parser.parse_args(argv)
    n_pairs = args.pairs or (20 if args.quick else 1000)
    K = 20 if args.quick else args.components
    n_np_loop = args.numpy_pairs or (2 if args.quick else 5)
    rng = np.random.default_rng(0)
    wa, ma, Pa = random_batch(rng, n_pairs, K)
    wb, mb, Pb = random_batch(rng, n_pairs, K)
    mask = jnp.ones((n_pairs, K), bool)
    A = GaussianMixture(jnp.asarray(wa), jnp.asarray(ma), jnp.asarray(Pa), mask)
    B = GaussianMixture(jnp.asarray(wb), jnp.asarray(mb), jnp.asarray(Pb), mask)

    batched = jax.jit(jax.vmap(metrics.ise))
    t_jax = time_jax(batched, A, B, repeats=3 if args.quick else 5)
    values = np.asarray(batched(A, B))

    # NumPy references in the same process: the explicit double loop (timed on a few pairs and scaled,
    # it is O(K^2) Python iterations per pair) and a broadcasting version over all pairs.
    loop_idx = range(n_np_loop)
    t_loop = time_python(
        lambda: [metrics_np.ise(wa[i], ma[i], Pa[i], wb[i], mb[i], Pb[i]) for i in loop_idx], repeats=1
    )
    per_pair_loop = t_loop["run_min_s"] / n_np_loop
    t_vec = time_python(
        lambda: [metrics_np.ise_vectorized(wa[i], ma[i], Pa[i], wb[i], mb[i], Pb[i]) for i in range(n_pairs)],
        repeats=1 if not args.quick else 2,
    )
    ref_vec = np.array(
        [metrics_np.ise_vectorized(wa[i], ma[i], Pa[i], wb[i], mb[i], Pb[i]) for i in range(min(n_pairs, 50))]
    )
    ref_loop = np.array([metrics_np.ise(wa[i], ma[i], Pa[i], wb[i], mb[i], Pb[i]) for i in loop_idx])
    max_rel_err = float(
        max(
            np.max(np.abs(values[: len(ref_vec)] - ref_vec) / np.abs(ref_vec)),
            np.max(np.abs(values[:n_np_loop] - ref_loop) / np.abs(ref_loop)),
        )
    )

    jax_per_pair = t_jax["run_min_s"] / n_pairs
    vec_per_pair = t_vec["run_min_s"] / n_pairs
    rows = [
        ["gmjax jit(vmap(ise))", n_pairs, t_jax["compile_s"], t_jax["run_min_s"], jax_per_pair * 1e6, 1.0],
        [
            "NumPy broadcasting loop over pairs",
            n_pairs,
            0.0,
            t_vec["run_min_s"],
            vec_per_pair * 1e6,
            vec_per_pair / jax_per_pair,
        ],
        [
            f"NumPy double loop (timed on {n_np_loop} pairs, scaled)",
            n_pairs,
            0.0,
            per_pair_loop * n_pairs,
            per_pair_loop * 1e6,
            per_pair_loop / jax_per_pair,
        ],
    ]
    header = ["implementation", "pairs", "compile s", "run s (min)", "µs / pair", "time ratio vs gmjax"]
    md = (
        f"# ISE between {n_pairs} pairs of {K}-component 2-D mixtures (float64)\n\n"
        + markdown_table(header, rows)
        + f"\n\nMax relative difference gmjax vs NumPy references: {max_rel_err:.2e}.\n"
        + "Time ratio > 1 means gmjax is faster. Measured in one process on "
        + f"{jax.devices()[0].platform.upper()} ({__import__('os').cpu_count()} cores).\n"
    )
    data = {
        "n_pairs": n_pairs,
        "components": K,
        "gmjax": t_jax,
        "numpy_vectorized": t_vec,
        "numpy_loop_per_pair_s": per_pair_loop,
        "speedup_vs_numpy_vectorized": vec_per_pair / jax_per_pair,
        "speedup_vs_numpy_loop": per_pair_loop / jax_per_pair,
        "max_rel_err": max_rel_err,
    }
    path = write_results("metrics", data, md, quick=args.quick)
    print(md)
    print(f"wrote {path}")
    return data


if __name__ == "__main__":
    main()
