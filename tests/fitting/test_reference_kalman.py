"""Self-checks of references/kalman_np.py (plain NumPy/SciPy, no JAX).

* ``kalman_loglik`` equals the joint Gaussian log-density of ``z_1..z_T`` built directly from
  ``F, H, Q, R, m0, P0`` (stacked mean and ``(T m, T m)`` covariance), also with missing rows.
* ``ml_noise_variances`` on simulated scalar random walks reaches a stationary point (gradient
  of the log-likelihood below 1e-6) near the true noise variances.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.stats import multivariate_normal

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from references import kalman_np  # noqa: E402


def _model():
    F = np.array([[1.0, 0.5], [0.0, 0.9]])
    H = np.array([[1.0, 0.3]])
    Q = np.array([[0.3, 0.05], [0.05, 0.2]])
    R = np.array([[0.7]])
    m0 = np.array([0.4, -0.2])
    P0 = np.array([[1.5, 0.2], [0.2, 0.8]])
    return F, H, Q, R, m0, P0


def _joint_measurements(F, H, Q, R, m0, P0, T):
    """Mean ``(T m,)`` and covariance ``(T m, T m)`` of the stacked ``z_1..z_T``, directly."""
    d, mz = F.shape[0], H.shape[0]
    Fp = [np.linalg.matrix_power(F, k) for k in range(T + 1)]
    # state covariances P_k = F^k P0 F^k' + sum_{i=1..k} F^{k-i} Q F^{k-i}'
    Pk = [
        Fp[k] @ P0 @ Fp[k].T + sum((Fp[k - i] @ Q @ Fp[k - i].T for i in range(1, k + 1)), np.zeros((d, d)))
        for k in range(T + 1)
    ]
    mean = np.concatenate([H @ Fp[k] @ m0 for k in range(1, T + 1)])
    cov = np.zeros((T * mz, T * mz))
    for k in range(1, T + 1):
        for l in range(k, T + 1):
            block = H @ Fp[l - k] @ Pk[k] @ H.T  # Cov(z_l, z_k), l >= k
            if l == k:
                block = block + R
            cov[(l - 1) * mz : l * mz, (k - 1) * mz : k * mz] = block
            cov[(k - 1) * mz : k * mz, (l - 1) * mz : l * mz] = block.T
    return mean, cov


def test_loglik_equals_joint_gaussian_density():
    F, H, Q, R, m0, P0 = _model()
    T = 6
    rng = np.random.default_rng(1)
    mean, cov = _joint_measurements(F, H, Q, R, m0, P0, T)
    for _ in range(5):
        zs = rng.multivariate_normal(mean, cov).reshape(T, 1)
        exact = multivariate_normal(mean, cov).logpdf(zs.reshape(-1))
        got = kalman_np.kalman_loglik(zs, F, H, Q, R, m0, P0)
        np.testing.assert_allclose(got, exact, rtol=1e-10, atol=0)
        # missing rows: the marginal density of the observed ones
        keep = np.array([True, False, True, True, False, True])
        zs_nan = zs.copy()
        zs_nan[~keep] = np.nan
        exact_m = multivariate_normal(mean[keep], cov[np.ix_(keep, keep)]).logpdf(zs[keep, 0])
        np.testing.assert_allclose(
            kalman_np.kalman_loglik(zs_nan, F, H, Q, R, m0, P0), exact_m, rtol=1e-10, atol=0
        )


def test_batch_is_sum_of_sequences():
    F, H, Q, R, m0, P0 = _model()
    rng = np.random.default_rng(2)
    zs = rng.normal(size=(4, 7, 1))
    zs[1, 3] = np.nan
    zs[2, 0] = np.nan
    each = [kalman_np.kalman_loglik(z, F, H, Q, R, m0, P0) for z in zs]
    np.testing.assert_allclose(kalman_np.kalman_loglik_batch(zs, F, H, Q, R, m0, P0), sum(each), rtol=1e-13)
    np.testing.assert_allclose(kalman_np.kalman_logliks(zs, F, H, Q, R, m0, P0), each, rtol=1e-13)


def test_ml_noise_variances_random_walk():
    rng = np.random.default_rng(20240607)
    B, T, q_true, r_true = 5, 100, 0.5, 2.0
    x = np.cumsum(rng.normal(0.0, np.sqrt(q_true), (B, T)), axis=1)  # x_0 = 0
    zs = (x + rng.normal(0.0, np.sqrt(r_true), (B, T)))[..., None]
    I = np.eye(1)
    m0, P0 = np.zeros(1), 1e-2 * I
    q, r, res = kalman_np.ml_noise_variances(zs, I, I, m0, P0, 1.0, 1.0, I, I)

    def loglik(theta):
        return kalman_np.kalman_loglik_batch(zs, I, I, np.exp(theta[0]) * I, np.exp(theta[1]) * I, m0, P0)

    theta = np.log([q, r])
    for h in (1e-3, 1e-4):
        g = kalman_np.central_gradient(loglik, theta, h)
        assert np.all(np.abs(g) < 1e-6), (h, g)
    # plain 2-point central differences agree too
    g2 = np.array([(loglik(theta + e) - loglik(theta - e)) / 2e-5 for e in np.eye(2) * 1e-5])
    assert np.all(np.abs(g2) < 1e-6), g2
    # a local maximum: every nearby point is lower
    for e in np.vstack([np.eye(2), -np.eye(2), [[1, 1], [1, -1]]]) * 1e-3:
        assert loglik(theta + e) < res.loglik
    np.testing.assert_allclose(res.loglik, loglik(theta), rtol=1e-14)
    assert 0.2 < q < 1.2 and 1.0 < r < 3.5, (q, r)
    # a second start reaches the same point to ~1e-8 relative
    q2, r2, _ = kalman_np.ml_noise_variances(zs, I, I, m0, P0, 0.05, 10.0, I, I)
    np.testing.assert_allclose([q2, r2], [q, r], rtol=1e-8)
