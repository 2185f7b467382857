"""Shared random-mixture helpers for the reduction tests (no tests here; seed 000 ranges)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from gmjax.mixture import GaussianMixture


def random_components(rng, n, d, *, wr=(1e-2, 0.2), xr=(-2.0, 4.0), sr=(0.4, 1.0)):
    """``n`` live components: weights in ``wr`` (normalised), means uniform in ``xr``, and
    covariances ``R diag(s^2) R^T`` with standard deviations uniform in ``sr``."""
    w = rng.uniform(*wr, n)
    w = w / w.sum()
    m = rng.uniform(*xr, (n, d))
    if d == 1:
        P = rng.uniform(*sr, (n, 1, 1)) ** 2
    else:
        P = np.empty((n, d, d))
        for k in range(n):
            q, _ = np.linalg.qr(rng.normal(size=(d, d)))
            P[k] = q @ np.diag(rng.uniform(*sr, d) ** 2) @ q.T
            P[k] = 0.5 * (P[k] + P[k].T)
    return w, m, P


def batch(comps, capacity, dtype=jnp.float64):
    """Stack ``[(w, m, P), ...]`` of varying sizes into one padded batched mixture (no
    normalisation; padded slots are (0, 0, I))."""
    B = len(comps)
    d = np.asarray(comps[0][1]).shape[1]
    W = np.zeros((B, capacity))
    M = np.zeros((B, capacity, d))
    C = np.broadcast_to(np.eye(d), (B, capacity, d, d)).copy()
    mask = np.zeros((B, capacity), bool)
    for b, (w, m, P) in enumerate(comps):
        n = len(w)
        W[b, :n], M[b, :n], C[b, :n], mask[b, :n] = w, m, P, True
    return GaussianMixture(
        jnp.asarray(W, dtype), jnp.asarray(M, dtype), jnp.asarray(C, dtype), jnp.asarray(mask)
    )


def index(gm, b):
    return jax.tree_util.tree_map(lambda a: a[b], gm)


def scatter_padding(gm: GaussianMixture, capacity: int, seed: int) -> GaussianMixture:
    """The same live components, in the same relative order, spread over a larger capacity with
    padded slots interleaved at random positions."""
    rng = np.random.default_rng(seed)
    n = int(np.sum(np.asarray(gm.mask)))
    pos = np.sort(rng.choice(capacity, n, replace=False))
    d = gm.dim
    W = np.zeros(capacity)
    M = np.zeros((capacity, d))
    C = np.broadcast_to(np.eye(d), (capacity, d, d)).copy()
    mask = np.zeros(capacity, bool)
    live = np.flatnonzero(np.asarray(gm.mask))
    W[pos] = np.asarray(gm.weights)[live]
    M[pos] = np.asarray(gm.means)[live]
    C[pos] = np.asarray(gm.covs)[live]
    mask[pos] = True
    dt = gm.weights.dtype
    return GaussianMixture(jnp.asarray(W, dt), jnp.asarray(M, dt), jnp.asarray(C, dt), jnp.asarray(mask))


def live_sorted(gm: GaussianMixture):
    """Live components as NumPy arrays sorted by (weight, first mean coordinate) for
    order-insensitive comparisons."""
    mask = np.asarray(gm.mask)
    w = np.asarray(gm.weights)[mask]
    m = np.asarray(gm.means)[mask]
    P = np.asarray(gm.covs)[mask]
    order = np.lexsort((m[:, 0], w))
    return w[order], m[order], P[order]


def seeded_mixture(seed, n=8, d=2, capacity=10, dtype=jnp.float64, **kw):
    """A mixture of ``n`` :func:`random_components` drawn with ``seed`` in ``capacity`` slots, and its
    ``(w, m, P)``."""
    rng = np.random.default_rng(seed)
    w, m, P = random_components(rng, n, d, **kw)
    return GaussianMixture.create(w, m, P, capacity=capacity, dtype=dtype), (w, m, P)


def reference_batch(d, seed, n=200, capacity=12):
    """``n`` random ``(w, m, P)`` of 6 to ``capacity`` components in ``d`` dimensions (seed 000
    ranges) and their capacity-``capacity`` batch, for comparing a vmapped reducer with a loop of
    its NumPy reference."""
    rng = np.random.default_rng(seed)
    comps = [random_components(rng, int(rng.integers(6, capacity + 1)), d) for _ in range(n)]
    return comps, batch(comps, capacity)


def assert_equals_reference(out, info, r, b, n):
    """Mixture ``b`` of a batched reducer's ``(out, info)`` equals the reference's result ``r`` (a
    dict of ``w``, ``m``, ``P``, ``labels``): outputs to 1e-10, labels exactly; ``n`` live inputs."""
    n_out = int(info.n_out[b])
    assert n_out == len(r["w"])
    np.testing.assert_allclose(np.asarray(out.weights[b, :n_out]), r["w"], rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.means[b, :n_out]), r["m"], rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.covs[b, :n_out]), r["P"], rtol=0, atol=1e-10)
    assert not np.asarray(out.mask[b, n_out:]).any()
    np.testing.assert_array_equal(np.asarray(info.labels[b, :n]), r["labels"])
    assert (np.asarray(info.labels[b, n:]) == -1).all()
