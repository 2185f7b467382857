"""Quadrature rules: exactness on every monomial up to the rule's degree against N(0, I), node
counts against the known formulas, FilterPy's Merwe points, transform, validation."""

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import quadrature as q


def _gauss_moment(exps) -> float:
    """E[prod z_j^a_j] for z ~ N(0, I): prod (a_j - 1)!! for even a_j, else 0 (closed form)."""
    out = 1.0
    for a in exps:
        if a % 2:
            return 0.0
        out *= math.prod(range(a - 1, 0, -2)) if a > 0 else 1.0
    return out


def _monomials(d, max_total):
    for exps in itertools.product(range(max_total + 1), repeat=d):
        if sum(exps) <= max_total:
            yield exps


def _rule_moment(rule, exps, weights="wm"):
    pts = np.asarray(rule.points)
    w = np.asarray(getattr(rule, weights))
    return float(np.sum(w * np.prod(pts ** np.asarray(exps), axis=1)))


def _assert_exact(rule, degree, d):
    for exps in _monomials(d, degree):
        got = _rule_moment(rule, exps)
        want = _gauss_moment(exps)
        assert abs(got - want) <= 1e-10 * max(1.0, abs(want)), (exps, got, want)


@pytest.mark.parametrize("d", range(1, 7))
def test_cubature_degree3_and_count(d):
    rule = q.cubature(d)
    assert rule.points.shape == (2 * d, d)
    _assert_exact(rule, 3, d)
    np.testing.assert_allclose(np.asarray(rule.wm), 1.0 / (2 * d))


@pytest.mark.parametrize("d", range(1, 7))
@pytest.mark.parametrize("params", [(1.0, 0.0, None), (0.5, 2.0, 0.0), (1e-1, 2.0, 1.0), (1.0, 2.0, 3.0)])
def test_unscented_degree3_count_and_cov_weight(d, params):
    alpha, beta, kappa = params
    rule = q.unscented(d, alpha, beta, kappa)
    assert rule.points.shape == (2 * d + 1, d)
    _assert_exact(rule, 3, d)
    # wc differs from wm only in the centre weight, by 1 - alpha^2 + beta (eq 27)
    np.testing.assert_allclose(float(jnp.sum(rule.wc)), 1.0 + 1.0 - alpha**2 + beta, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(rule.wc[1:]), np.asarray(rule.wm[1:]))


def test_unscented_default_kappa_matches_fourth_moment():
    # kappa = 3 - d puts the points at +-sqrt(3): E[z_j^4] = 3 is also exact.
    for d in (1, 2, 3, 4):
        rule = q.unscented(d)
        exps = [0] * d
        exps[0] = 4
        assert abs(_rule_moment(rule, exps) - 3.0) < 1e-10


@pytest.mark.parametrize("d,alpha,beta,kappa", [(2, 1e-3, 2.0, 0.0), (4, 0.3, 2.0, -1.0), (3, 1.0, 0.0, 0.0)])
def test_unscented_matches_filterpy_merwe(d, alpha, beta, kappa):
    from filterpy.kalman import MerweScaledSigmaPoints

    sp = MerweScaledSigmaPoints(d, alpha=alpha, beta=beta, kappa=kappa)
    rng = np.random.default_rng(0)
    mean = rng.normal(size=d)
    A = rng.normal(size=(d, d))
    P = A @ A.T + d * np.eye(d)
    rule = q.unscented(d, alpha, beta, kappa)
    pts = q.transform(rule, mean, P)
    np.testing.assert_allclose(np.asarray(pts), sp.sigma_points(mean, P), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(rule.wm), sp.Wm, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(rule.wc), sp.Wc, rtol=1e-12)


@pytest.mark.parametrize("d,order", [(1, 1), (1, 5), (2, 3), (3, 2), (3, 3), (4, 2), (5, 2), (6, 2)])
def test_gauss_hermite_exact_per_coordinate(d, order):
    rule = q.gauss_hermite(d, order)
    assert rule.points.shape == (order**d, d)
    deg = 2 * order - 1
    # every monomial with each exponent <= 2 order - 1 (the tensor rule's exactness)
    cap = min(deg, 3) if d >= 5 else deg
    for exps in itertools.product(range(cap + 1), repeat=d):
        got = _rule_moment(rule, exps)
        want = _gauss_moment(exps)
        assert abs(got - want) <= 1e-9 * max(1.0, want), (exps, got, want)


def test_gauss_hermite_not_exact_beyond_degree():
    # independence check that the monomial test can fail: z^(2n) is not exact for n nodes
    rule = q.gauss_hermite(1, 3)
    assert abs(_rule_moment(rule, (6,)) - 15.0) > 1.0


@pytest.mark.parametrize("growth", ["linear", "exponential"])
@pytest.mark.parametrize("d", range(1, 7))
@pytest.mark.parametrize("level", [1, 2, 3])
def test_smolyak_exact_to_degree_2L_minus_1(d, level, growth):
    rule = q.smolyak(d, level, growth)
    _assert_exact(rule, 2 * level - 1, d)
    np.testing.assert_allclose(float(jnp.sum(rule.wm)), 1.0, rtol=1e-12)


def test_smolyak_level2_fails_on_a_degree4_cross_term():
    rule = q.smolyak(3, 2)
    assert abs(_rule_moment(rule, (2, 2, 0)) - 1.0) > 0.5  # E[z1^2 z2^2] = 1 not reproduced


def test_smolyak_counts():
    assert q.smolyak(6, 2).num_points == 13  # seed 002 §V: level 2 in 6-D
    assert q.smolyak(6, 2, "exponential").num_points == 13
    for d in range(1, 8):
        assert q.smolyak(d, 1).num_points == 1
        # level 2: centre + 2d axis points at +-sqrt(3); the centre weight 2d/3 - (d-1)
        # cancels for d = 3, and a zero-weight node is dropped
        assert q.smolyak(d, 2).num_points == (2 * d if d == 3 else 2 * d + 1)
        # level 3 (linear growth): centre, 6 points per axis (5-point rule + 3-point rule),
        # 4 points per coordinate plane (3x3 product minus its axis points); in 1-D the
        # level-3 rule is the 5-point Gauss-Hermite rule alone
        if 2 <= d <= 6:
            assert q.smolyak(d, 3).num_points == 1 + 6 * d + 2 * d * (d - 1)
    assert q.smolyak(1, 3).num_points == 5
    # negative weights are kept (the level-2 centre in 6-D has weight 6 * 2/3 - 5 = -1)
    rule = q.smolyak(6, 2)
    centre = np.all(np.asarray(rule.points) == 0, axis=1)
    np.testing.assert_allclose(np.asarray(rule.wm)[centre], [-1.0], rtol=1e-12)


def test_smolyak_1d_equals_gauss_hermite():
    for level in (1, 2, 3, 4):
        s = q.smolyak(1, level)
        g = q.gauss_hermite(1, 2 * level - 1)
        order = np.argsort(np.asarray(g.points)[:, 0])
        np.testing.assert_allclose(np.asarray(s.points)[:, 0], np.asarray(g.points)[order, 0], atol=1e-12)
        np.testing.assert_allclose(np.asarray(s.wm), np.asarray(g.wm)[order], rtol=1e-10)


def test_transform_and_expectation_match_closed_form():
    rng = np.random.default_rng(1)
    d = 3
    mean = rng.normal(size=d)
    A = rng.normal(size=(d, d))
    P = A @ A.T + np.eye(d)
    B = rng.normal(size=(d, d))
    B = B + B.T
    want = np.trace(B @ P) + mean @ B @ mean  # E[x^T B x]
    for rule in (q.cubature(d), q.unscented(d, 0.5, 2.0, 1.0), q.gauss_hermite(d, 2), q.smolyak(d, 2)):
        got = q.expectation(rule, lambda x: x @ jnp.asarray(B) @ x, mean, P)
        np.testing.assert_allclose(float(got), want, rtol=1e-10)
        L = np.linalg.cholesky(P)
        p1 = q.transform(rule, mean, P)
        p2 = q.transform(rule, mean, L, is_chol=True)
        np.testing.assert_allclose(np.asarray(p1), np.asarray(p2), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(p1), mean + np.asarray(rule.points) @ L.T, atol=1e-12)


def test_transform_jit_vmap_and_float32():
    rule32 = q.cubature(2, dtype=jnp.float32)
    assert rule32.points.dtype == jnp.float32
    means = jnp.arange(6.0, dtype=jnp.float32).reshape(3, 2)
    covs = jnp.broadcast_to(jnp.eye(2, dtype=jnp.float32), (3, 2, 2))
    out = jax.jit(jax.vmap(lambda m, P: q.transform(rule32, m, P)))(means, covs)
    assert out.dtype == jnp.float32
    for i in range(3):
        np.testing.assert_allclose(out[i], q.transform(rule32, means[i], covs[i]), rtol=1e-6)


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="d:"):
        q.cubature(0)
    with pytest.raises(ValueError, match="alpha"):
        q.unscented(2, alpha=0.0)
    with pytest.raises(ValueError, match="kappa"):
        q.unscented(2, alpha=1.0, kappa=-3.0)
    with pytest.raises(ValueError, match="order"):
        q.gauss_hermite(2, 0)
    with pytest.raises(ValueError, match="level"):
        q.smolyak(2, 0)
    with pytest.raises(ValueError, match="growth"):
        q.smolyak(2, 2, growth="cubic")
    with pytest.raises(ValueError, match="beta"):
        q.unscented(2, beta=float("nan"))
