import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from gmjax import GaussianMixture, gaussian, metrics
from gmjax import mixture as mx


def gm_1d(seed, K, capacity=None, dtype=None):
    rng = np.random.default_rng(seed)
    return GaussianMixture.create(
        rng.uniform(0.05, 1, K),
        rng.uniform(-2, 3, K),
        rng.uniform(0.2, 1.5, K) ** 2,
        capacity=capacity,
        dtype=dtype,
    )


def gm_2d(seed, K, capacity=None):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(K, 2, 2)) * 0.6
    P = A @ np.swapaxes(A, 1, 2) + 0.3 * np.eye(2)
    return GaussianMixture.create(rng.uniform(0.05, 1, K), rng.uniform(-2, 2, (K, 2)), P, capacity=capacity)


def dense_ise_1d(a, b):
    x = np.linspace(-15, 18, 40001)[:, None]
    fa, fb = np.asarray(mx.pdf(a, x)), np.asarray(mx.pdf(b, x))
    return np.trapezoid((fa - fb) ** 2, x[:, 0]), np.trapezoid(fa**2, x[:, 0]), np.trapezoid(fb**2, x[:, 0])


def dense_ise_2d(a, b):
    g = np.linspace(-10, 10, 601)
    X, Y = np.meshgrid(g, g, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel()], -1)
    fa = np.asarray(mx.pdf(a, pts)).reshape(X.shape)
    fb = np.asarray(mx.pdf(b, pts)).reshape(X.shape)
    integ = lambda F: np.trapezoid(np.trapezoid(F, g, axis=1), g)  # noqa: E731
    return integ((fa - fb) ** 2), integ(fa**2), integ(fb**2)


def test_ise_nise_match_dense_integration_1d():
    a, b = gm_1d(0, 6, capacity=8), gm_1d(1, 3)
    ise_n, jaa, jbb = dense_ise_1d(a, b)
    np.testing.assert_allclose(metrics.ise(a, b), ise_n, rtol=1e-8)
    np.testing.assert_allclose(metrics.l2_norm_sq(a), jaa, rtol=1e-8)
    np.testing.assert_allclose(metrics.nise(a, b), ise_n / (jaa + jbb), rtol=1e-8)


def test_ise_nise_match_dense_integration_2d():
    a, b = gm_2d(2, 5), gm_2d(3, 2, capacity=4)
    ise_n, jaa, jbb = dense_ise_2d(a, b)
    np.testing.assert_allclose(metrics.ise(a, b), ise_n, rtol=1e-6)
    np.testing.assert_allclose(metrics.nise(a, b), ise_n / (jaa + jbb), rtol=1e-6)


def test_cross_overlap_entries_and_padding_zero():
    a, b = gm_1d(4, 2, capacity=3), gm_1d(5, 3)
    S = np.asarray(metrics.cross_overlap(a, b))
    assert S.shape == (3, 3)
    np.testing.assert_allclose(S[2], 0.0)
    for i in range(2):
        for j in range(3):
            m1, p1 = float(a.means[i, 0]), float(a.covs[i, 0, 0])
            m2, p2 = float(b.means[j, 0]), float(b.covs[j, 0, 0])
            np.testing.assert_allclose(S[i, j], stats.norm(m2, np.sqrt(p1 + p2)).pdf(m1), rtol=1e-12)


def test_ise_properties():
    a, b = gm_2d(6, 4), gm_2d(7, 3)
    assert float(metrics.ise(a, a)) < 1e-15
    np.testing.assert_allclose(metrics.ise(a, b), metrics.ise(b, a), rtol=1e-12)
    n = float(metrics.nise(a, b))
    assert 0.0 <= n <= 1.0


def test_results_unchanged_by_padding_anywhere():
    a, b = gm_2d(8, 3), gm_2d(9, 2)
    a_pad = mx.concat(
        mx.pad(jax.tree_util.tree_map(lambda x: x[:1], a), 4), jax.tree_util.tree_map(lambda x: x[1:], a)
    )
    b_pad = mx.pad(b, 5)
    for f in (metrics.ise, metrics.nise, metrics.l2_inner):
        np.testing.assert_allclose(f(a_pad, b_pad), f(a, b), rtol=1e-13)


def test_grad_through_ise_with_padded_slots_is_finite():
    a, b = gm_2d(10, 3, capacity=6), gm_2d(11, 2, capacity=4)

    def loss(weights, means, covs):
        return metrics.ise(GaussianMixture(weights, means, covs, a.mask), b)

    grads = jax.grad(loss, argnums=(0, 1, 2))(a.weights, a.means, a.covs)
    for g in grads:
        assert np.all(np.isfinite(g))
    # padded slots get exactly zero gradient
    np.testing.assert_allclose(grads[0][3:], 0.0)
    np.testing.assert_allclose(grads[1][3:], 0.0)
    # and the live-weight gradient matches central finite differences
    eps = 1e-6
    e0 = jnp.zeros(6).at[0].set(eps)
    fd = (loss(a.weights + e0, a.means, a.covs) - loss(a.weights - e0, a.means, a.covs)) / (2 * eps)
    np.testing.assert_allclose(grads[0][0], fd, rtol=1e-6)


def test_jit_equals_eager_vmap_equals_loop():
    pairs = [(gm_2d(20 + i, 4, capacity=5), gm_2d(40 + i, 2, capacity=5)) for i in range(3)]
    A = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[p[0] for p in pairs])
    B = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[p[1] for p in pairs])
    batched = jax.jit(jax.vmap(metrics.ise))(A, B)
    loop = [metrics.ise(a, b) for a, b in pairs]
    np.testing.assert_allclose(batched, loop, rtol=1e-12)
    np.testing.assert_allclose(jax.jit(metrics.nise)(*pairs[0]), metrics.nise(*pairs[0]), rtol=1e-12)


def test_float32_close_to_float64():
    a64, b64 = gm_1d(30, 5), gm_1d(31, 2)
    a32, b32 = gm_1d(30, 5, dtype=jnp.float32), gm_1d(31, 2, dtype=jnp.float32)
    v32 = metrics.nise(a32, b32)
    assert v32.dtype == jnp.float32
    np.testing.assert_allclose(v32, metrics.nise(a64, b64), rtol=1e-4)


def test_kl_mc_matches_closed_form_within_standard_error():
    a = GaussianMixture.create([1.0], [[0.0, 1.0]], [[[1.0, 0.3], [0.3, 2.0]]], capacity=3)
    b = GaussianMixture.create([1.0], [[0.5, 0.0]], [[[1.5, 0.0], [0.0, 1.0]]])
    exact = gaussian.kl_divergence(a.means[0], a.covs[0], b.means[0], b.covs[0])
    est, se = jax.jit(lambda k: metrics.kl_mc_with_stderr(a, b, k, 100_000))(jax.random.key(0))
    assert abs(float(est) - float(exact)) < 5 * float(se)
    self_kl = jax.jit(lambda k: metrics.kl_mc(a, a, k, 1000))(jax.random.key(1))
    assert float(self_kl) == pytest.approx(0.0, abs=1e-12)


def test_estimation_metrics_match_numpy():
    rng = np.random.default_rng(50)
    N, T, d = 6, 5, 3
    est = rng.normal(size=(N, T, d))
    truth = rng.normal(size=(N, T, d))
    A = rng.normal(size=(N, T, d, d))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(d)
    err = est - truth
    sq = (err**2).sum(-1)
    np.testing.assert_allclose(metrics.rmse(est, truth), np.sqrt(sq.mean(0)), rtol=1e-13)
    np.testing.assert_allclose(metrics.rmse(est, truth, axis=None), np.sqrt(sq.mean()), rtol=1e-13)
    nees = np.einsum("nti,ntij,ntj->nt", err, np.linalg.inv(P), err)
    np.testing.assert_allclose(metrics.nees(est, P, truth), nees, rtol=1e-11)
    np.testing.assert_allclose(metrics.anees(est, P, truth), nees.mean(), rtol=1e-11)
    np.testing.assert_allclose(metrics.anees(est, P, truth, per_dim=True), nees.mean() / d, rtol=1e-11)
    np.testing.assert_allclose(metrics.cep(est, truth), np.median(np.sqrt(sq)), rtol=1e-13)
    np.testing.assert_allclose(metrics.cep(est, truth, axis=0), np.median(np.sqrt(sq), axis=0), rtol=1e-13)


def test_nees_of_consistent_gaussian_errors_averages_to_dimension():
    rng = np.random.default_rng(51)
    n, d = 50_000, 2
    P = np.array([[2.0, 0.5], [0.5, 1.0]])
    err = rng.multivariate_normal(np.zeros(d), P, size=n)
    values = np.asarray(metrics.nees(err, np.broadcast_to(P, (n, d, d)), np.zeros((n, d))))
    # NEES ~ chi2(d): mean d, standard deviation sqrt(2d)
    assert abs(values.mean() - d) < 5 * np.sqrt(2 * d / n)
