"""gmjax.reduction, every reducer alike: invariants (jit == eager, vmap == loop, padding, float32,
threshold gradients), bad input, and the brute-force oracle. One reducer's own tests are in the file
named for its module (test_merge.py, test_prune.py, test_pcm.py, ...)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_reduction_utils import batch, index, live_sorted, random_components, scatter_padding, seeded_mixture

from gmjax import reduction as R
from gmjax.metrics import ise as _ise_eager
from gmjax.mixture import GaussianMixture

ise = jax.jit(_ise_eager)


# ----------------------------------------------------------------------------- reducer invariants

NUM_OUT = 3

REDUCERS = {
    "runnalls": lambda g, t=jnp.inf: R.runnalls(g, NUM_OUT, t),
    "west": lambda g, t=jnp.inf: R.west(g, NUM_OUT, t),
    "salmond": lambda g, t=jnp.inf: R.salmond(g, NUM_OUT, t),
    "williams": lambda g, t=jnp.inf: R.williams(g, NUM_OUT, t),
    "cowa": lambda g, t=jnp.inf: R.cowa(g, NUM_OUT, t),
    "gmrc": lambda g, t=None: R.gmrc(g, NUM_OUT),
    "kmeans": lambda g, t=None: R.kmeans(g, NUM_OUT),
    "vo_ma": lambda g, t=4.0: R.vo_ma(g, 1e-3, t),
    "prune_threshold": lambda g, t=0.05: R.prune_threshold(g, t),
    "prune_censored": lambda g, t=0.9: R.prune_censored(g, t),
    "prune_top": lambda g, t=None: R.prune_top(g, NUM_OUT),
    "brute_force": lambda g, t=None: R.brute_force(g, NUM_OUT),
}
THRESHOLDED = [
    "runnalls",
    "west",
    "salmond",
    "williams",
    "cowa",
    "vo_ma",
    "prune_threshold",
    "prune_censored",
]
CAP = 9


def _assert_same(a, b, atol=1e-12):
    for x, y in zip(a, b):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=atol, rtol=0)


def _batch_with_spread(seed):
    """Three mixtures of 6, 7, 5 components in capacity ``CAP`` (live slots first) and the first one
    again with its live slots scattered among padded ones."""
    rng = np.random.default_rng(seed)
    comps = [random_components(rng, n, 2) for n in (6, 7, 5)]
    gms = batch(comps, CAP)
    spread = scatter_padding(index(gms, 0), CAP, seed=seed)
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b[None]]), gms, spread)


@pytest.mark.parametrize("name", list(REDUCERS))
def test_jit_vmap_padding(name):
    """jit(vmap(f)) == [f(g) for g] (f's own jit is the eager entry point); total weight is kept;
    interleaving padded slots changes neither the components nor the labels of live slots."""
    fn = REDUCERS[name]
    gms = _batch_with_spread(len(name))
    eager = [fn(index(gms, b)) for b in range(4)]
    out_v, info_v = jax.jit(jax.vmap(fn))(gms)
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(out_v))
    for b in range(4):
        out_e, info_e = eager[b]
        _assert_same(index(out_v, b), out_e)
        np.testing.assert_array_equal(np.asarray(info_v.labels[b]), np.asarray(info_e.labels))
        assert int(info_v.n_out[b]) == int(info_e.n_out)
        w_in = float(jnp.sum(index(gms, b).weights))
        assert abs(float(jnp.sum(out_e.weights)) - w_in) < 1e-12
    g0, spread = index(gms, 0), index(gms, 3)
    (out0, info0), (out_p, info_p) = eager[0], eager[3]
    for x, y in zip(live_sorted(out_p), live_sorted(out0)):
        np.testing.assert_allclose(x, y, atol=1e-12)
    lab_p = np.asarray(info_p.labels)[np.asarray(spread.mask)]
    lab_e = np.asarray(info0.labels)[np.asarray(g0.mask)]
    np.testing.assert_array_equal(lab_p < 0, lab_e < 0)
    means_p = np.asarray(out_p.means)[np.maximum(lab_p, 0)]
    means_e = np.asarray(out0.means)[np.maximum(lab_e, 0)]
    np.testing.assert_allclose(means_p[lab_p >= 0], means_e[lab_e >= 0], atol=1e-12)


HEAVY = {"williams", "cowa", "gmrc", "brute_force"}  # compile-heavy: float32/grad checks are slow


def _maybe_slow(names):
    return [pytest.param(n, marks=pytest.mark.slow) if n in HEAVY else n for n in names]


@pytest.mark.parametrize("name", _maybe_slow(REDUCERS))
def test_float32(name):
    fn = REDUCERS[name]
    rng = np.random.default_rng(100 + len(name))
    w, m, P = random_components(rng, 6, 2)
    g64 = GaussianMixture.create(w, m, P, capacity=CAP)
    g32 = GaussianMixture.create(w, m, P, capacity=CAP, dtype=jnp.float32)
    o64, _ = fn(g64)
    o32, i32 = fn(g32)
    assert o32.weights.dtype == jnp.float32 and o32.covs.dtype == jnp.float32
    for x, y in zip(live_sorted(o32), live_sorted(o64)):
        np.testing.assert_allclose(x, y, rtol=2e-4, atol=2e-5)


@pytest.mark.parametrize("name", _maybe_slow(THRESHOLDED))
def test_threshold_gradient(name):
    fn = REDUCERS[name]
    gm, _ = seeded_mixture(7, n=6, d=2, capacity=CAP)
    t0 = {"vo_ma": 4.0, "prune_threshold": 0.05, "prune_censored": 0.9}.get(name, 0.5)

    def loss(t):
        out, info = fn(gm, t)
        return ise(gm, out) + jnp.sum(out.means) + info.cost

    g = jax.grad(loss)(jnp.asarray(t0))
    assert np.isfinite(float(g))


def test_fewer_live_than_target_unchanged_inside_jit():
    gm, _ = seeded_mixture(8, n=3, d=2, capacity=CAP)
    for name in ["runnalls", "west", "salmond", "williams", "cowa", "gmrc", "kmeans", "brute_force"]:
        out, info = REDUCERS[name](gm)  # the implementation is a jitted kernel
        _assert_same(out, gm, atol=1e-15)
        assert int(info.n_out) == 3 and int(info.n_in) == 3
        np.testing.assert_array_equal(np.asarray(info.labels), [0, 1, 2] + [-1] * (CAP - 3))


def test_threshold_stops_early():
    gm, _ = seeded_mixture(9, n=8, d=2, capacity=CAP)
    _, full = R.runnalls(gm, 1)
    counts = []
    for thr in (0.0, 1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0):
        out, info = R.runnalls(gm, 1, thr)
        merges = np.asarray(info.aux["merges"])
        n_merged = int((merges[:, 0] >= 0).sum())
        assert int(info.n_out) == 8 - n_merged
        # a prefix of the unbounded merge sequence
        np.testing.assert_array_equal(merges[:n_merged], np.asarray(full.aux["merges"])[:n_merged])
        counts.append(int(info.n_out))
    assert counts == sorted(counts, reverse=True) and counts[0] == 8
    assert any(1 < c < 8 for c in counts)


# ----------------------------------------------------------------------------- bad input


def test_bad_input_raises():
    gm, _ = seeded_mixture(10, n=5, d=2, capacity=6)
    with pytest.raises(ValueError, match="num_out"):
        R.runnalls(gm, 0)
    with pytest.raises(ValueError, match="num_out"):
        R.kmeans(gm, 7)
    with pytest.raises(ValueError, match="threshold"):
        R.west(gm, 2, -1.0)
    with pytest.raises(ValueError, match="threshold"):
        R.prune_threshold(gm, float("nan"))
    with pytest.raises(ValueError, match="rho"):
        R.prune_censored(gm, 1.5)
    with pytest.raises(ValueError, match="capacity"):
        R.salmond(gm, 3, capacity=2)
    bad = gm._replace(means=gm.means.at[1, 0].set(jnp.nan))
    with pytest.raises(ValueError, match="means"):
        R.williams(bad, 2)
    with pytest.raises(ValueError, match="weights"):
        R.gmrc(gm._replace(weights=gm.weights.at[0].set(-0.1)), 2)
    with pytest.raises(ValueError, match="method"):
        R.merge_labels(gm, jnp.zeros(6, int), 2, "median")
    with pytest.raises(ValueError, match="merge_threshold"):
        R.vo_ma(gm, 0.1, -2.0)


# ----------------------------------------------------------------------------- brute-force oracle


def test_configs_are_reducers():
    gm, _ = seeded_mixture(12, n=6, d=2, capacity=CAP)
    cfgs = [
        R.Runnalls(num_out=3),
        R.West(num_out=3),
        R.Salmond(num_out=3),
        R.KMeans(num_out=3),
        R.PruneTop(num_out=3),
        R.VoMa(prune_threshold=1e-3),
    ]
    for cfg in cfgs:
        leaves, tree = jax.tree_util.tree_flatten(cfg)
        cfg2 = jax.tree_util.tree_unflatten(tree, leaves)
        out, info = cfg2(gm)
        assert out.capacity == CAP and int(info.n_out) >= 1
