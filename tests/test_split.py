"""Tests for gmjax.split: libraries (moments, L2 optimality), eq 20 splits, seed 001 eq 32, refine."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, optimize
from scipy.stats import norm

from gmjax import mixture
from gmjax.mixture import GaussianMixture
from gmjax.split import (
    gauss_hermite_library,
    library_l2_error,
    library_moments,
    principal_library,
    refine,
    split_axis,
    split_gaussian,
    split_mixture,
    split_principal,
    split_repeated,
    uniform_library,
)

_pdf = jax.jit(mixture.pdf)
_moments = jax.jit(mixture.moments)


def _normal_moment(p):
    return 0.0 if p % 2 else float(np.prod(np.arange(p - 1, 0, -2))) if p else 1.0


def _random_spd(rng, d):
    A = rng.standard_normal((d, d))
    return A @ A.T + d * np.eye(d)


def _lib_pdf(lib, x):
    return sum(w * norm.pdf(x, m, float(lib.sigma)) for w, m in zip(lib.weights, lib.means))


# ---------------------------------------------------------------------------------------------
# libraries
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("num,sigma", [(8, 0.5), (16, 1 / 40), (3, 0.8), (5, 0.3)])
def test_gauss_hermite_library_matches_normal_moments_to_order_2m_minus_1(num, sigma):
    lib = gauss_hermite_library(num, sigma)
    assert lib.size == num
    np.testing.assert_allclose(lib.weights.sum(), 1.0, rtol=1e-14)
    np.testing.assert_allclose(
        float(lib.sigma) ** 2,
        1 - (lib.means[-1] / np.polynomial.hermite_e.hermegauss(num)[0][-1]) ** 2,
        rtol=1e-12,
    )
    orders = list(range(0, 2 * num))
    got = library_moments(lib, orders)
    want = np.array([_normal_moment(p) for p in orders])
    # odd moments vanish; compare them on the scale of the neighbouring even moment (rounding)
    scale = np.array([max(1.0, _normal_moment(p + (p % 2))) for p in orders])
    np.testing.assert_allclose(got / scale, want / scale, rtol=1e-10, atol=1e-13)
    # independent check of two moments by adaptive quadrature of the library density
    for p in (2, 4) if sigma > 0.1 else ():
        val, _ = integrate.quad(lambda x: x**p * _lib_pdf(lib, x), -np.inf, np.inf, limit=400)
        np.testing.assert_allclose(val, _normal_moment(p), rtol=1e-7)


@pytest.mark.parametrize("lib_fn", [lambda: gauss_hermite_library(8, 0.5), lambda: uniform_library(0.5)])
def test_library_l2_error_matches_scipy_quadrature_and_closed_form(lib_fn):
    lib = lib_fn()
    E = library_l2_error(lib)
    val, _ = integrate.quad(
        lambda x: (norm.pdf(x) - _lib_pdf(lib, x)) ** 2,
        -np.inf,
        np.inf,
        limit=500,
        epsabs=1e-18,
        epsrel=1e-10,
    )
    np.testing.assert_allclose(E, val, rtol=1e-5, atol=1e-17)
    # closed form of eq 13 (c - 2 b^T w + w^T G w)
    w, mu, s = lib.weights, lib.means, float(lib.sigma)
    G = norm.pdf(mu[:, None] - mu[None, :], 0, math.sqrt(2) * s)
    b = norm.pdf(mu, 0, math.sqrt(1 + s * s))
    closed = 1 / (2 * math.sqrt(math.pi)) - 2 * b @ w + w @ G @ w
    np.testing.assert_allclose(E, closed, rtol=1e-4, atol=1e-14)


@pytest.mark.parametrize("sigma,M", [(0.25, 49), (1 / 3, 37), (0.5, 17), (0.6, 15), (0.1, 121)])
def test_uniform_library_layout_follows_eqs_14_to_16(sigma, M):
    lib = uniform_library(sigma)
    m = 6.0 if sigma < 0.5 else 4.0
    assert lib.size == M == math.ceil(1 + 2 * m / sigma - 1e-9)
    np.testing.assert_allclose(lib.means, -m + sigma * np.arange(M), rtol=0, atol=1e-12)
    assert float(lib.sigma) == pytest.approx(sigma)
    assert np.all(lib.weights >= 0)
    np.testing.assert_allclose(lib.weights.sum(), 1.0, rtol=1e-13)


@pytest.mark.parametrize("sigma", [0.25, 0.5, 0.6])
def test_uniform_library_weights_are_l2_optimal(sigma):
    """KKT optimality of the w >= 0, sum w = 1 QP, and no better point found by SLSQP."""
    lib = uniform_library(sigma)
    w, mu = lib.weights, lib.means
    G = norm.pdf(mu[:, None] - mu[None, :], 0, math.sqrt(2) * sigma)
    b = norm.pdf(mu, 0, math.sqrt(1 + sigma * sigma))
    c = 1 / (2 * math.sqrt(math.pi))
    obj = lambda v: c - 2 * b @ v + v @ G @ v  # noqa: E731
    res = optimize.minimize(
        obj,
        np.full(len(mu), 1 / len(mu)),
        jac=lambda v: -2 * b + 2 * G @ v,
        method="SLSQP",
        bounds=[(0, None)] * len(mu),
        constraints=[{"type": "eq", "fun": lambda v: v.sum() - 1}],
        options={"ftol": 1e-16, "maxiter": 2000},
    )
    assert obj(w) <= res.fun + 1e-12
    # the library approximates N(0, 1) far better than the Gauss-Hermite one with the same sigma
    assert library_l2_error(lib) < 1e-9
    assert library_l2_error(lib) < library_l2_error(gauss_hermite_library(lib.size, sigma))
    # mean and variance close to N(0, 1) (the L2 fit does not match moments exactly)
    mom = library_moments(lib, [1, 2])
    np.testing.assert_allclose(mom, [0.0, 1.0], atol=1e-4)


def test_library_bad_arguments_raise():
    with pytest.raises(ValueError, match="sigma"):
        gauss_hermite_library(4, 1.0)
    with pytest.raises(ValueError, match="sigma"):
        uniform_library(0.0)
    with pytest.raises(ValueError, match="num"):
        gauss_hermite_library(0, 0.5)
    with pytest.raises(ValueError, match="l"):
        principal_library(1.5)
    with pytest.raises(ValueError, match="w"):
        principal_library(0.5, 0.0)


# ---------------------------------------------------------------------------------------------
# splitting a Gaussian (eq 20)
# ---------------------------------------------------------------------------------------------


def test_split_along_axis_zero_is_eq_20_with_cholesky_factor():
    rng = np.random.default_rng(0)
    d = 3
    P = _random_spd(rng, d)
    mu = rng.standard_normal(d)
    lib = gauss_hermite_library(5, 0.4)
    gm = split_gaussian(0.7, mu, P, lib, direction=0)
    L = np.linalg.cholesky(P)
    for i in range(lib.size):
        mu_d = np.zeros(d)
        mu_d[0] = lib.means[i]
        S_d = np.eye(d)
        S_d[0, 0] = float(lib.sigma) ** 2
        np.testing.assert_allclose(gm.means[i], mu + L @ mu_d, rtol=1e-12)  # eq 20 mean
        np.testing.assert_allclose(gm.covs[i], L @ S_d @ L.T, rtol=1e-12, atol=1e-12)  # eq 20 cov
        np.testing.assert_allclose(gm.weights[i], 0.7 * lib.weights[i], rtol=1e-13)


@pytest.mark.parametrize("direction", [None, 0, 2, "vec"])
def test_gauss_hermite_split_preserves_mean_and_covariance(direction):
    rng = np.random.default_rng(1)
    d = 3
    P = _random_spd(rng, d)
    mu = rng.standard_normal(d)
    if direction == "vec":
        direction = rng.standard_normal(d)
    gm = split_gaussian(1.0, mu, P, gauss_hermite_library(6, 0.5), direction=direction)
    m, C = _moments(gm)
    np.testing.assert_allclose(m, mu, atol=1e-12)
    np.testing.assert_allclose(C, P, rtol=1e-12, atol=1e-12)
    for k in range(6):
        assert np.all(np.linalg.eigvalsh(np.asarray(gm.covs[k])) > 0)


def test_split_axis_for_a_vector_splits_its_marginal_with_the_library():
    """Along u the marginal of u^T x is split exactly as the 1-D library splits N(u^T mu, u^T P u)."""
    rng = np.random.default_rng(2)
    d = 3
    P = _random_spd(rng, d)
    mu = rng.standard_normal(d)
    u = rng.standard_normal(d)
    lib = uniform_library(0.5)
    gm = split_gaussian(1.0, mu, P, lib, direction=u)
    s = math.sqrt(u @ P @ u)
    np.testing.assert_allclose(np.asarray(gm.means) @ u, u @ mu + s * lib.means, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        np.einsum("i,kij,j->k", u, np.asarray(gm.covs), u), (s * float(lib.sigma)) ** 2, rtol=1e-12
    )
    a = np.asarray(split_axis(P, u))
    np.testing.assert_allclose(a, P @ u / s, rtol=1e-12)


def test_split_principal_one_pass_is_seed001_eq32():
    rng = np.random.default_rng(3)
    d = 4
    P = _random_spd(rng, d)
    mu = rng.standard_normal(d)
    l, w = 0.5, 0.3
    gm = split_principal(2.0, mu, P, 1, l=l, w=w)
    lam, V = np.linalg.eigh(P)
    e = V[:, -1]
    lam = lam[-1]
    sign = np.sign(np.dot(np.asarray(gm.means[0]) - mu, e))
    np.testing.assert_allclose(gm.means[0], mu + sign * l * math.sqrt(lam) * e, rtol=1e-10)
    np.testing.assert_allclose(gm.means[1], mu - sign * l * math.sqrt(lam) * e, rtol=1e-10)
    for k in range(2):
        np.testing.assert_allclose(gm.covs[k], P - l * l * lam * np.outer(e, e), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(gm.weights, [2.0 * w, 2.0 * (1 - w)], rtol=1e-14)


@pytest.mark.parametrize("n", [0, 1, 2, 3])
def test_split_principal_repeated_gives_2_to_n_and_keeps_moments(n):
    rng = np.random.default_rng(4)
    d = 3
    P = _random_spd(rng, d)
    mu = rng.standard_normal(d)
    gm = split_principal(1.0, mu, P, n)
    assert gm.capacity == 2**n
    m, C = _moments(gm)
    np.testing.assert_allclose(m, mu, atol=1e-10)
    np.testing.assert_allclose(C, P, rtol=1e-10, atol=1e-10)
    if n >= 2:  # each pass splits along the *current* principal axis of every child
        first = split_principal(1.0, mu, P, 1)
        lam_child = np.linalg.eigvalsh(np.asarray(first.covs[0]))[-1]
        lam_gchild = np.linalg.eigvalsh(np.asarray(gm.covs[0]))[-1]
        assert lam_gchild < lam_child


def test_split_repeated_1d_benchmark_prior_has_4096_terms_with_unit_moments():
    lib = gauss_hermite_library(8, 0.5)
    gm = split_repeated(mixture.from_gaussian(jnp.zeros(1), jnp.eye(1)), lib, [0] * 4)
    assert gm.capacity == 4096
    m, C = _moments(gm)
    np.testing.assert_allclose(m, [0.0], atol=1e-12)
    np.testing.assert_allclose(C, [[1.0]], rtol=1e-12)
    np.testing.assert_allclose(gm.covs[:, 0, 0], (0.25**4) * np.ones(4096), rtol=1e-12)
    # repeated Gauss-Hermite splits keep the higher moments of N(0, 1) too
    w, m, v = (np.asarray(a).reshape(4096) for a in (gm.weights, gm.means, gm.covs))
    np.testing.assert_allclose(w @ (m**4 + 6 * m**2 * v + 3 * v**2), 3.0, rtol=1e-11)
    np.testing.assert_allclose(w @ (m**6 + 15 * m**4 * v + 45 * m**2 * v**2 + 15 * v**3), 15.0, rtol=1e-11)


# ---------------------------------------------------------------------------------------------
# split_mixture / refine
# ---------------------------------------------------------------------------------------------


def _gm(rng, n, d, capacity=None, dtype=jnp.float64):
    w = rng.uniform(0.1, 1.0, n)
    m = rng.standard_normal((n, d))
    P = np.stack([_random_spd(rng, d) for _ in range(n)])
    return GaussianMixture.create(w, m, P, capacity=capacity, dtype=dtype)


def test_split_mixture_padding_is_harmless_and_gradient_finite():
    rng = np.random.default_rng(5)
    gm = _gm(rng, 3, 2)
    gm_pad = mixture.pad(gm, 6)
    lib = gauss_hermite_library(4, 0.5)
    a = split_mixture(gm, lib, None)
    b = split_mixture(gm_pad, lib, None)
    assert b.capacity == 24
    np.testing.assert_allclose(b.weights[:12], a.weights, rtol=1e-14)
    np.testing.assert_allclose(b.means[:12], a.means, rtol=1e-14)
    assert not np.any(np.asarray(b.mask[12:]))
    np.testing.assert_array_equal(b.covs[12:], np.broadcast_to(np.eye(2), (12, 2, 2)))

    def loss(means):
        out = split_mixture(gm_pad._replace(means=means), lib, 0)
        return jnp.sum(out.weights[:, None] * out.means**2) + jnp.sum(out.covs)

    g = jax.grad(loss)(gm_pad.means)
    assert np.all(np.isfinite(np.asarray(g)))


def test_refine_splits_selected_slots_and_matches_manual_concat():
    rng = np.random.default_rng(6)
    gm = _gm(rng, 3, 2, capacity=12)
    lib = gauss_hermite_library(3, 0.5)
    sel = jnp.array([True, False, True] + [False] * 9)
    out, info = refine(gm, sel, lib, direction=1)
    assert int(info.n_split) == 2 and int(info.n_out) == 7 and not bool(info.overflow)
    manual = mixture.concat(
        mixture.concat(
            split_gaussian(gm.weights[0], gm.means[0], gm.covs[0], lib, 1),
            GaussianMixture(gm.weights[1:2], gm.means[1:2], gm.covs[1:2], gm.mask[1:2]),
        ),
        split_gaussian(gm.weights[2], gm.means[2], gm.covs[2], lib, 1),
    )
    x = rng.standard_normal((20, 2))
    np.testing.assert_allclose(_pdf(out, x), _pdf(manual, x), rtol=1e-12)
    # order: children next to their parent
    np.testing.assert_allclose(out.means[3], gm.means[1], rtol=1e-14)
    np.testing.assert_allclose(mixture.total_weight(out), mixture.total_weight(gm), rtol=1e-13)
    mixture.check(out)


def test_refine_overflow_splits_heaviest_first():
    gm = GaussianMixture.create([0.1, 0.6, 0.3], [[0.0], [1.0], [2.0]], [1.0, 1.0, 1.0], capacity=6)
    lib = gauss_hermite_library(3, 0.5)  # each split needs 2 free slots; 3 are free
    out, info = refine(gm, jnp.ones(6, bool), lib)
    assert bool(info.overflow) and int(info.n_split) == 1 and int(info.n_out) == 5
    # the heaviest slot (index 1) was split: its three children follow slot 0
    np.testing.assert_allclose(out.weights[1:4], 0.6 * lib.weights, rtol=1e-13)
    np.testing.assert_allclose(np.asarray(out.weights)[[0, 4]], [0.1, 0.3], rtol=1e-13)
    out2, info2 = refine(gm, jnp.ones(6, bool), lib, capacity=9)
    assert not bool(info2.overflow) and int(info2.n_out) == 9


def test_refine_jit_vmap_float32_and_padding():
    rng = np.random.default_rng(7)
    lib = principal_library()
    gms = [_gm(rng, 2, 2, capacity=5) for _ in range(3)]
    sels = [jnp.array([True, True, False, False, False])] * 3
    eager = [refine(g, s, lib)[0] for g, s in zip(gms, sels)]
    jitted = jax.jit(lambda g, s: refine(g, s, lib)[0])
    batched = jax.vmap(lambda g, s: refine(g, s, lib)[0])(
        jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gms), jnp.stack(sels)
    )
    for i, (g, s) in enumerate(zip(gms, sels)):
        j = jitted(g, s)
        np.testing.assert_allclose(j.means, eager[i].means, rtol=1e-12)
        np.testing.assert_allclose(batched.covs[i], eager[i].covs, rtol=1e-12)
        np.testing.assert_array_equal(batched.mask[i], eager[i].mask)
    # extra padded slots do not change the live result
    g_pad = mixture.pad(gms[0], 9)
    out_pad, _ = refine(g_pad, jnp.concatenate([sels[0], jnp.zeros(4, bool)]), lib)
    x = rng.standard_normal((10, 2))
    np.testing.assert_allclose(_pdf(out_pad, x), _pdf(eager[0], x), rtol=1e-12)
    # float32
    g32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, gms[0])
    out32, _ = refine(g32, sels[0], lib)
    assert out32.means.dtype == jnp.float32
    np.testing.assert_allclose(out32.covs, eager[0].covs, rtol=1e-5, atol=1e-5)


def test_refine_bad_arguments_raise():
    gm = GaussianMixture.create([1.0], [[0.0]], [1.0], capacity=2)
    lib = gauss_hermite_library(2, 0.5)
    with pytest.raises(ValueError, match="capacity"):
        refine(gm, jnp.ones(2, bool), lib, capacity=1)
    with pytest.raises(ValueError, match="mask_to_split"):
        refine(gm, jnp.ones(3, bool), lib)
    with pytest.raises(ValueError, match="direction"):
        split_gaussian(1.0, jnp.zeros(2), jnp.eye(2), lib, direction=5)
    with pytest.raises(ValueError, match="n_split"):
        split_principal(1.0, jnp.zeros(2), jnp.eye(2), -1)
