"""gmjax.reduction._greedy, the pairwise-merge engine of Runnalls, Salmond and West: merge sequences and
outputs against the NumPy references (random mixtures, a cost threshold, exact ties), and under vmap in
blocks against the loop, with gradients."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_reducer_gradients import padded_mixture
from test_reduction_utils import (
    assert_equals_reference,
    batch,
    reference_batch,
)

from gmjax import GaussianMixture
from gmjax import reduction as R
from gmjax.reduction import _greedy
from references import reduction_np as ref

CAP = 12
NUM_OUT = 4


@pytest.mark.parametrize("d", [1, 2])
@pytest.mark.parametrize("name", ["runnalls", "salmond", "west", "west_ise"])
def test_greedy_matches_numpy(name, d):
    comps, gm = reference_batch(d, seed=10 * d + len(name))
    if name == "west_ise":
        fn = jax.jit(jax.vmap(lambda g: R.west(g, NUM_OUT, metric="ise")))
        reff = lambda w, m, P: ref.west(w, m, P, NUM_OUT, metric="ise")  # noqa: E731
    else:
        fn = jax.jit(jax.vmap(lambda g: getattr(R, name)(g, NUM_OUT)))
        reff = lambda w, m, P: getattr(ref, name)(w, m, P, NUM_OUT)  # noqa: E731
    out, info = fn(gm)
    for b, (w, m, P) in enumerate(comps):
        r = reff(w, m, P)
        merges = [tuple(int(v) for v in row) for row in np.asarray(info.aux["merges"][b]) if row[0] >= 0]
        assert merges == r["merges"], f"mixture {b}: merge sequence differs"
        assert_equals_reference(out, info, r, b, len(w))
        np.testing.assert_allclose(float(info.cost[b]), r["cost"], rtol=1e-9, atol=1e-12)


def test_greedy_threshold_matches_numpy():
    """A finite cost threshold stops Runnalls/Salmond at the same step as the reference."""
    comps, gm = reference_batch(2, seed=77, n=20)
    for name, thr in (("runnalls", 0.02), ("salmond", 0.05)):
        out, info = jax.vmap(lambda g: getattr(R, name)(g, 1, thr))(gm)
        for b, (w, m, P) in enumerate(comps):
            r = getattr(ref, name)(w, m, P, 1, thr)
            assert_equals_reference(out, info, r, b, len(w))


@pytest.mark.parametrize("name", ["runnalls", "salmond"])
def test_greedy_ties_match_numpy(name):
    """Many exactly equal pair costs (equal weights and covariances, means on an integer lattice,
    repeated components): the selection takes the first minimiser in row-major order, as the
    reference's ``argmin`` over the upper triangle does. (In 1-D: a 2-D lattice also
    has pairs equal only mathematically, e.g. offsets (1.5, 0.5) and (0.5, 1.5), whose costs round
    differently here and in NumPy.)"""
    d = 1
    rng = np.random.default_rng(3 + d)
    comps = []
    for _ in range(40):
        n = int(rng.integers(6, CAP + 1))
        m = rng.integers(0, 3, (n, d)).astype(float)
        comps.append((np.full(n, 1.0 / n), m, np.tile(np.eye(d), (n, 1, 1))))
    gm = batch(comps, CAP)
    out, info = jax.jit(jax.vmap(lambda g: getattr(R, name)(g, 2)))(gm)
    for b, (w, m, P) in enumerate(comps):
        r = getattr(ref, name)(w, m, P, 2)
        merges = [tuple(int(v) for v in row) for row in np.asarray(info.aux["merges"][b]) if row[0] >= 0]
        assert merges == r["merges"], f"mixture {b}: merge sequence differs"
        assert_equals_reference(out, info, r, b, len(w))


@pytest.mark.parametrize("name", ["runnalls", "salmond"])
def test_jit_grad_of_vmapped_greedy_reducers_equals_the_loop(name):
    """``jit(grad(vmap(...)))`` of Runnalls and Salmond equals the per-mixture gradients (it once
    failed with an ``IndexError`` when they batched as a sequential map with a custom rule; they
    now batch as blocks of a plain ``vmap``, with the same guard for it)."""
    reducer = {"runnalls": R.Runnalls(num_out=3), "salmond": R.Salmond(num_out=3)}[name]
    gms = [padded_mixture(seed) for seed in (1, 2)]
    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gms)

    def scalar(means, gm):
        out, _ = reducer(gm._replace(means=means))
        return jnp.sum(out.weights[:, None] * out.means**2)

    batched = jax.jit(jax.grad(lambda m: jax.vmap(scalar)(m, batch).sum()))(batch.means)
    for i, gm in enumerate(gms):
        np.testing.assert_allclose(batched[i], jax.grad(scalar)(gm.means, gm), rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("name", ["runnalls", "salmond"])
def test_greedy_reducers_batched_in_blocks_equal_the_loop_and_differentiate(name):
    """Runnalls at d >= 3 and Salmond run under ``vmap`` in blocks of ``_greedy.BLOCK`` mixtures
    (``_greedy.chunked``); over a batch of two blocks and a remainder the outputs equal the
    per-mixture calls bit for bit, and ``jit(grad(vmap))`` equals the per-mixture gradients."""
    d, K, n = 3, 8, 2 * _greedy.BLOCK + 5
    rng = np.random.default_rng(7)
    A = rng.normal(size=(n, K, d, d))
    w = rng.uniform(0.2, 1.0, (n, K))
    batch = GaussianMixture(
        jnp.asarray(w / w.sum(1, keepdims=True)),
        jnp.asarray(rng.normal(0.0, 2.0, (n, K, d))),
        jnp.asarray(0.2 * np.eye(d) + 0.3 * A @ np.swapaxes(A, -1, -2)),
        jnp.ones((n, K), bool),
    )
    reducer = {"runnalls": R.Runnalls(num_out=3), "salmond": R.Salmond(num_out=3)}[name]
    out_v, info_v = jax.jit(jax.vmap(reducer))(batch)
    for b in (0, _greedy.BLOCK, n - 1):
        gm = jax.tree_util.tree_map(lambda a, b=b: a[b], batch)
        out, info = reducer(gm)
        for x, y in zip(jax.tree_util.tree_leaves((out, info)), jax.tree_util.tree_leaves((out_v, info_v))):
            np.testing.assert_array_equal(np.asarray(y[b]), np.asarray(x))

    # nothing to merge (an empty merge sequence, a zero-size output of every block)
    same, info_same = jax.vmap(type(reducer)(num_out=K))(batch)
    assert info_same.aux["merges"].shape == (n, 0, 2)
    np.testing.assert_array_equal(same.weights, batch.weights)

    def scalar(means, gm):
        out, _ = reducer(gm._replace(means=means))
        return jnp.sum(out.weights[:, None] * out.means**2)

    grads = jax.jit(jax.grad(lambda m: jax.vmap(scalar)(m, batch).sum()))(batch.means)
    for b in (0, n - 1):
        gm = jax.tree_util.tree_map(lambda a, b=b: a[b], batch)
        np.testing.assert_allclose(grads[b], jax.grad(scalar)(gm.means, gm), rtol=1e-12, atol=1e-14)
