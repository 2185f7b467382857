"""OSPA / GOSPA / the exact assignment of gmjax.multitarget.metrics against SciPy and Stone Soup."""

import datetime

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment as scipy_lsa

from gmjax.multitarget import metrics
from references.ospa_np import gospa_ref, ospa_ref


def _random_sets(rng, n_sets, cap_x, cap_y, d=2, scale=10.0):
    """Padded sets with random sizes 0..cap (including empty sets) and their masks."""
    out = []
    for _ in range(n_sets):
        nx, ny = rng.integers(0, cap_x + 1), rng.integers(0, cap_y + 1)
        x = rng.normal(size=(cap_x, d)) * scale
        y = rng.normal(size=(cap_y, d)) * scale
        mx = np.zeros(cap_x, bool)
        mx[rng.choice(cap_x, nx, replace=False)] = True
        my = np.zeros(cap_y, bool)
        my[rng.choice(cap_y, ny, replace=False)] = True
        out.append((x, mx, y, my))
    return out


@pytest.mark.parametrize("n", [1, 2, 4, 7])
def test_assignment_is_optimal_like_scipy(n):
    rng = np.random.default_rng(n)
    Cs = rng.normal(size=(30, n, n))
    Cs[::3] = np.round(Cs[::3])  # ties
    cols = np.asarray(jax.jit(jax.vmap(metrics.linear_sum_assignment))(jnp.asarray(Cs)))
    for C, col in zip(Cs, cols):
        assert sorted(col.tolist()) == list(range(n))  # a permutation
        r, k = scipy_lsa(C)
        np.testing.assert_allclose(C[np.arange(n), col].sum(), C[r, k].sum(), rtol=0, atol=1e-12)


@jax.jit
def _batched_metrics(X, Y, MX, MY, c, p):
    """OSPA and GOSPA over a batch of padded set pairs, ``c`` and ``p`` traced (one compile)."""
    o = jax.vmap(lambda x, y, mx, my: metrics.ospa(x, y, mx, my, c=c, p=p))(X, Y, MX, MY)
    g = jax.vmap(lambda x, y, mx, my: metrics.gospa(x, y, mx, my, c=c, p=p))(X, Y, MX, MY)
    return o, g


@pytest.mark.parametrize("c,p", [(5.0, 1.0), (20.0, 2.0), (8.0, 3.0)])
def test_ospa_gospa_equal_bruteforce_reference(c, p):
    rng = np.random.default_rng(int(c * p))
    sets = _random_sets(rng, 40, 6, 5)
    X, MX, Y, MY = (np.stack(a) for a in zip(*sets))
    o, g = _batched_metrics(X, Y, MX, MY, c, p)
    for i, (x, mx, y, my) in enumerate(sets):
        np.testing.assert_allclose(o[i], ospa_ref(x[mx], y[my], c=c, p=p), rtol=1e-10, atol=1e-12)
        ref = gospa_ref(x[mx], y[my], c=c, p=p)
        for name in ("distance", "localisation", "missed", "false"):
            np.testing.assert_allclose(getattr(g, name)[i], ref[name], rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(
            g.distance[i] ** p, g.localisation[i] + g.missed[i] + g.false[i], rtol=1e-10, atol=1e-9
        )
    # vmap == loop (one pair through the unbatched function)
    o0 = metrics.ospa(X[0], Y[0], MX[0], MY[0], c=c, p=p)
    np.testing.assert_allclose(o0, o[0], rtol=1e-13)


def test_metrics_edge_cases_and_jit_equals_eager():
    x = jnp.array([[0.0, 0.0], [10.0, 0.0]])
    y = jnp.array([[0.0, 1.0]])
    # closed form: one pair at distance 1, one point unmatched
    np.testing.assert_allclose(metrics.ospa(x, y, c=5.0, p=1.0), (1.0 + 5.0) / 2)
    g = metrics.gospa(x, y, c=5.0, p=1.0)
    np.testing.assert_allclose([g.localisation, g.missed, g.false], [1.0, 0.0, 2.5])
    assert float(metrics.ospa(x, y, jnp.zeros(2, bool), jnp.zeros(1, bool), c=5.0)) == 0.0
    np.testing.assert_allclose(metrics.ospa(x, y, None, jnp.zeros(1, bool), c=5.0), 5.0)
    np.testing.assert_allclose(metrics.gospa(x, y, jnp.zeros(2, bool), None, c=5.0, p=2.0).missed, 12.5)
    jit_o = jax.jit(lambda a, b: metrics.ospa(a, b, c=5.0, p=2.0))(x, y)
    np.testing.assert_allclose(jit_o, metrics.ospa(x, y, c=5.0, p=2.0), rtol=1e-14)
    with pytest.raises(ValueError, match="x_mask"):
        metrics.ospa(x, y, jnp.ones(3, bool))
    with pytest.raises(ValueError, match="cost"):
        metrics.linear_sum_assignment(jnp.ones((2, 3)))


def test_float32_matches_float64():
    rng = np.random.default_rng(3)
    x, y = rng.normal(size=(5, 2)) * 4, rng.normal(size=(4, 2)) * 4
    o64 = metrics.ospa(x, y, c=3.0, p=2.0)
    o32 = metrics.ospa(x.astype(np.float32), y.astype(np.float32), c=3.0, p=2.0)
    assert o32.dtype == jnp.float32
    np.testing.assert_allclose(o32, o64, rtol=1e-5)
    g32 = metrics.gospa(x.astype(np.float32), y.astype(np.float32), c=3.0, p=2.0)
    np.testing.assert_allclose(g32.distance, gospa_ref(x, y, c=3.0, p=2.0)["distance"], rtol=1e-5)


def test_soft_gospa_is_gospa_at_binary_weights_and_differentiable():
    rng = np.random.default_rng(5)
    x, y = rng.normal(size=(6, 2)) * 5, rng.normal(size=(4, 2)) * 5
    e = np.array([1.0, 0.0, 1.0, 1.0, 0.0, 1.0])
    s = metrics.soft_gospa(x, y, e, c=4.0, p=2.0)
    h = metrics.gospa(x, y, e > 0, c=4.0, p=2.0)
    for a, b in zip(s, h):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    # gradient w.r.t. the existence weights matches central differences (assignment unique here)
    e_soft = jnp.asarray([0.9, 0.2, 0.7, 0.6, 0.1, 0.8])

    def f(ee):
        return metrics.soft_gospa(x, y, ee, c=4.0, p=2.0).distance ** 2

    g = jax.grad(f)(e_soft)
    eps = 1e-6
    fd = np.array([(f(e_soft.at[i].add(eps)) - f(e_soft.at[i].add(-eps))) / (2 * eps) for i in range(6)])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)
    gx = jax.grad(lambda xx: metrics.gospa(xx, y, c=4.0, p=2.0).distance)(jnp.asarray(x))
    assert np.all(np.isfinite(gx))


def _stonesoup_states(points, t):
    from stonesoup.types.state import State

    return [State(np.asarray(pt, float).reshape(-1, 1), timestamp=t) for pt in points]


@pytest.mark.parametrize("c,p", [(5.0, 1.0), (12.0, 2.0)])
def test_ospa_gospa_equal_stonesoup(c, p):
    """Stone Soup's OSPA/GOSPA on the same sets.

    Stone Soup 1.9.1's ``OSPAMetric`` solves the assignment on the cut-off distances ``min(d, c)`` and
    then sums their ``p``-th powers, so for ``p > 1`` its value can exceed the OSPA (the minimum over
    assignments of the sum of ``min(d, c)^p``): there we check equality with SciPy's assignment on
    ``min(d, c)`` evaluated the same way, and that our OSPA is never larger. Its GOSPA assigns on
    ``min(d, c)^p`` and agrees to rounding.
    """
    pytest.importorskip("stonesoup")
    from stonesoup.metricgenerator.ospametric import GOSPAMetric, OSPAMetric

    t = datetime.datetime(2024, 1, 1)
    rng = np.random.default_rng(11)
    sets = _random_sets(rng, 25, 5, 5)
    X, MX, Y, MY = (np.stack(a) for a in zip(*sets))
    o, g = _batched_metrics(X, Y, MX, MY, c, p)
    ospa_ss = OSPAMetric(c=c, p=p)
    gospa_ss = GOSPAMetric(c=c, p=p)
    n_checked = 0
    for i, (x, mx, y, my) in enumerate(sets):
        xs, ys = _stonesoup_states(x[mx], t), _stonesoup_states(y[my], t)
        if xs or ys:
            ref = ospa_ss.compute_OSPA_distance(xs, ys).value
            if p == 1:
                np.testing.assert_allclose(o[i], ref, rtol=1e-10, atol=1e-12)
            else:
                assert o[i] <= ref + 1e-12
                n = max(len(xs), len(ys))
                D = np.full((n, n), c)
                D[: len(xs), : len(ys)] = np.minimum(np.linalg.norm(x[mx][:, None] - y[my][None], axis=-1), c)
                r, k = scipy_lsa(D)
                np.testing.assert_allclose(ref, (np.sum(D[r, k] ** p) / n) ** (1 / p), rtol=1e-12)
        if xs and ys:  # Stone Soup's GOSPA decomposition for empty sets has a sign quirk (negative counts)
            ref_g = gospa_ss.compute_gospa_metric(xs, ys)[0].value
            for name in ("distance", "localisation", "missed", "false"):
                np.testing.assert_allclose(getattr(g, name)[i], ref_g[name], rtol=1e-10, atol=1e-9)
            n_checked += 1
    assert n_checked >= 10
