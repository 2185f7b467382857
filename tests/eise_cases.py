"""Mixtures and helpers the EISE, search, PCM and GMRCM tests share (tests/reduction/eise/, test_pcm.py,
test_gmrcm.py)."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from gmjax.mixture import GaussianMixture
from gmjax.reduction.clustering import gauss_cluster
from references.pcm_numpy import STATIC_CASES

K = 12  # one capacity throughout so compiled kernels are shared


CASES = STATIC_CASES  # seed 000 §IV-A


def case(name, dtype=jnp.float64, capacity=K):
    w, m, s = CASES[name]
    return GaussianMixture.create(w, m, np.asarray(s, float) ** 2, capacity=capacity, dtype=dtype)


def case_np(name):
    w, m, s = CASES[name]
    return np.asarray(w, float), np.asarray(m, float)[:, None], (np.asarray(s, float) ** 2)[:, None, None]


def random_gm(seed, n=10, d=1, capacity=K, dtype=jnp.float64):
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.02, 0.2, n)
    m = rng.uniform(-2, 4, (n, d))
    A = rng.normal(size=(n, d, d)) * 0.3
    P = A @ np.swapaxes(A, 1, 2) + np.eye(d) * rng.uniform(0.16, 1.0, (n, 1, 1))
    gm = GaussianMixture.create(w, m, P, capacity=capacity, dtype=dtype)
    return gm, w / w.sum(), m, P


@partial(jax.jit, static_argnames="G")  # compiled once per shape, shared by the tests
def _grid_for(gm, G=11, lo=1.0, hi=3.0):
    grid = jnp.linspace(lo, hi, G)
    labels = jax.vmap(lambda lam: gauss_cluster(gm, lam).labels)(grid)
    counts = jax.vmap(lambda lab: jnp.unique(lab, size=K, fill_value=-1))(labels)
    counts = jnp.sum(counts >= 0, axis=1)
    return grid, labels, counts


NEWTON_TOL = 1e-9  # relative: Newton's hard EISE may exceed the grid's best only by rounding
