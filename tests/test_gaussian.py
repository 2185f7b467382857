import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from gmjax import gaussian


def random_spd(rng, d, scale=1.0):
    A = rng.normal(size=(d, d))
    return scale * (A @ A.T + d * np.eye(d) * 0.5)


@pytest.mark.parametrize("d", [1, 2, 4])
def test_logpdf_matches_scipy(d):
    rng = np.random.default_rng(d)
    m, P, x = rng.normal(size=d), random_spd(rng, d), rng.normal(size=d)
    expected = stats.multivariate_normal(m, P).logpdf(x)
    np.testing.assert_allclose(gaussian.logpdf(x, m, P), expected, rtol=1e-12)
    np.testing.assert_allclose(gaussian.pdf(x, m, P), np.exp(expected), rtol=1e-12)


def test_product_normalizer_matches_numerical_integral():
    # 1-D: ∫ N(x; m1, p1) N(x; m2, p2) dx by dense quadrature.
    m1, p1, m2, p2 = 0.3, 0.7, -0.4, 1.9
    x = np.linspace(-20, 20, 200001)
    integrand = stats.norm(m1, np.sqrt(p1)).pdf(x) * stats.norm(m2, np.sqrt(p2)).pdf(x)
    numeric = np.trapezoid(integrand, x)
    closed = gaussian.product_normalizer(
        jnp.array([m1]), jnp.array([[p1]]), jnp.array([m2]), jnp.array([[p2]])
    )
    np.testing.assert_allclose(closed, numeric, rtol=1e-9)


def test_mahalanobis_and_kl():
    rng = np.random.default_rng(0)
    d = 3
    m1, m2 = rng.normal(size=d), rng.normal(size=d)
    P1, P2 = random_spd(rng, d), random_spd(rng, d)
    r = m1 - m2
    np.testing.assert_allclose(gaussian.mahalanobis_sq(m1, m2, P2), r @ np.linalg.solve(P2, r), rtol=1e-12)
    np.testing.assert_allclose(
        gaussian.mahalanobis(m1, m2, P2), np.sqrt(r @ np.linalg.solve(P2, r)), rtol=1e-12
    )
    P2i = np.linalg.inv(P2)
    kl = 0.5 * (np.trace(P2i @ P1) + r @ P2i @ r - d + np.log(np.linalg.det(P2) / np.linalg.det(P1)))
    np.testing.assert_allclose(gaussian.kl_divergence(m1, P1, m2, P2), kl, rtol=1e-11)
    np.testing.assert_allclose(gaussian.kl_divergence(m1, P1, m1, P1), 0.0, atol=1e-12)
    # from a carried inverse and log-determinants (West's greedy loop): the same divergence, batched
    for dim in (1, 2, 3, 4):
        ms = rng.normal(size=(5, dim))
        Ps = np.stack([random_spd(rng, dim) for _ in range(5)])
        lds = np.linalg.slogdet(Ps)[1]
        got = gaussian.spd_kl_from_inverse(ms[0], Ps[0], lds[0], ms, np.linalg.inv(Ps), lds)
        want = [gaussian.spd_kl(ms[0], Ps[0], ms[k], Ps[k]) for k in range(5)]
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(gaussian.inv_spd(P1), np.linalg.inv(P1), rtol=1e-10)
    np.testing.assert_allclose(gaussian.logdet(P1), np.linalg.slogdet(P1)[1], rtol=1e-12)


def test_mahalanobis_gradient_finite_at_zero():
    g = jax.grad(lambda x: gaussian.mahalanobis(x, jnp.zeros(2), jnp.eye(2)))(jnp.zeros(2))
    assert np.all(np.isfinite(g))


def test_safe_cholesky_pd_is_exact_and_unflagged():
    rng = np.random.default_rng(1)
    P = random_spd(rng, 4)
    res = gaussian.safe_cholesky(P)
    assert not bool(res.repaired)
    assert float(res.jitter) == 0.0
    np.testing.assert_allclose(res.factor, np.linalg.cholesky(P), rtol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_safe_cholesky_repairs_indefinite_and_flags(dtype):
    P = jnp.array([[1.0, 2.0], [2.0, 1.0]], dtype)  # eigenvalues 3, -1
    res = jax.jit(gaussian.safe_cholesky)(P)
    assert bool(res.repaired)
    assert np.all(np.isfinite(res.factor))
    rebuilt = res.factor @ res.factor.T
    assert np.linalg.eigvalsh(np.asarray(rebuilt, np.float64))[0] > 0
    # the repair adds jitter on the diagonal only
    np.testing.assert_allclose(
        rebuilt - np.asarray(res.jitter) * np.eye(2), P, atol=1e-5 if dtype == jnp.float32 else 1e-12
    )


def test_safe_cholesky_gradient_finite_for_pd_and_repaired():
    def f(P):
        return jnp.sum(gaussian.safe_cholesky(P).factor)

    for P in (jnp.eye(3), jnp.array([[1.0, 2.0], [2.0, 1.0]])):
        g = jax.grad(f)(P)
        assert np.all(np.isfinite(g))


def test_logpdf_float32_close_to_float64():
    rng = np.random.default_rng(3)
    m, P, x = rng.normal(size=3), random_spd(rng, 3), rng.normal(size=3)
    v64 = gaussian.logpdf(x, m, P)
    v32 = gaussian.logpdf(
        jnp.asarray(x, jnp.float32), jnp.asarray(m, jnp.float32), jnp.asarray(P, jnp.float32)
    )
    assert v32.dtype == jnp.float32
    np.testing.assert_allclose(v32, v64, rtol=1e-5)


def test_jit_equals_eager_and_vmap_equals_loop():
    rng = np.random.default_rng(4)
    xs = rng.normal(size=(5, 2))
    ms = rng.normal(size=(5, 2))
    Ps = np.stack([random_spd(rng, 2) for _ in range(5)])
    batched = jax.jit(jax.vmap(gaussian.logpdf))(xs, ms, Ps)
    looped = [gaussian.logpdf(x, m, P) for x, m, P in zip(xs, ms, Ps)]
    np.testing.assert_allclose(batched, looped, rtol=1e-13)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_safe_cholesky_of_zero_covariance_is_finite_and_flagged(dtype):
    # e.g. a particle cloud that collapsed to one point
    res = jax.jit(gaussian.safe_cholesky)(jnp.zeros((2, 2), dtype))
    assert bool(res.repaired)
    assert np.all(np.isfinite(res.factor)) and float(res.jitter) > 0
    assert np.isfinite(
        float(gaussian.mahalanobis_sq(jnp.ones(2, dtype), jnp.zeros(2, dtype), jnp.zeros((2, 2), dtype)))
    )


@pytest.mark.parametrize("d", [1, 2, 3])
def test_spd_kernels_equal_scipy_and_the_safe_functions(d):
    """The broadcasting ``spd_*`` kernels (closed forms for d <= 2) against SciPy and the per-Gaussian
    functions, over a leading batch axis."""
    rng = np.random.default_rng(d)
    A = rng.normal(size=(4, d, d))
    P = A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(d)
    B = rng.normal(size=(4, d, d))
    Q = B @ np.swapaxes(B, -1, -2) + 0.5 * np.eye(d)
    x, m = rng.normal(size=(4, d)), rng.normal(size=(4, d))
    Pj, Qj, xj, mj = (jnp.asarray(a, jnp.float64) for a in (P, Q, x, m))
    np.testing.assert_allclose(gaussian.spd_logdet(Pj), np.linalg.slogdet(P)[1], rtol=1e-12)
    np.testing.assert_allclose(gaussian.spd_inv(Pj), np.linalg.inv(P), rtol=1e-10, atol=1e-12)
    quad = np.einsum("ni,nij,nj->n", x, np.linalg.inv(P), x)
    np.testing.assert_allclose(gaussian.spd_inv_quad(xj, Pj), quad, rtol=1e-12)
    ref = [stats.multivariate_normal(m[i], P[i]).logpdf(x[i]) for i in range(4)]
    np.testing.assert_allclose(gaussian.spd_logpdf(xj, mj, Pj), ref, rtol=1e-12)
    kl = jax.vmap(gaussian.kl_divergence)(mj, Pj, xj, Qj)
    np.testing.assert_allclose(gaussian.spd_kl(mj, Pj, xj, Qj), kl, rtol=1e-10)


def test_moment_merge_pair_preserves_the_moments():
    w1, w2 = 0.3, 0.5
    m1, m2 = np.array([0.0, 1.0]), np.array([2.0, -1.0])
    P1, P2 = np.diag([1.0, 2.0]), np.array([[1.0, 0.3], [0.3, 0.5]])
    W, m, P = gaussian.moment_merge_pair(*(jnp.asarray(a, jnp.float64) for a in (w1, m1, P1, w2, m2, P2)))
    mean = (w1 * m1 + w2 * m2) / (w1 + w2)
    second = (w1 * (P1 + np.outer(m1, m1)) + w2 * (P2 + np.outer(m2, m2))) / (w1 + w2)
    np.testing.assert_allclose(W, w1 + w2, rtol=1e-15)
    np.testing.assert_allclose(m, mean, rtol=1e-14)
    np.testing.assert_allclose(P, second - np.outer(mean, mean), rtol=1e-13, atol=1e-15)
