"""Self-checks of references/gm_noise_np.py (plain NumPy/SciPy, no JAX).

* One-component mixture: ``grid_loglik`` equals the Kalman filter's exact log-likelihood
  (references/kalman_np.py), missing measurement included.
* Two-component mixture, short sequence: ``grid_loglik`` equals the exact likelihood summed over
  all ``2^T`` measurement-noise histories (one Kalman filter each).
* Known state (``q = p0 = 1e-12``, ``a = 1``, ``m0 = 0``): ``grid_loglik`` equals the i.i.d.
  mixture log-likelihood (cell-averaged kernel, see the module docstring), and ``ml_fit_grid``
  equals ``em_iid`` on the same samples.
* ``em_iid`` recovers a known mixture from 20000 samples, its log-likelihood at least the truth's.
"""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import numpy as np
from scipy.special import logsumexp

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from references import gm_noise_np, kalman_np  # noqa: E402

W2, MU2, S2 = np.array([0.3, 0.7]), np.array([-1.5, 0.8]), np.array([0.4, 1.2])


def _simulate(rng, a, q, m0, p0, T, weights, means, variances):
    x = m0 + np.sqrt(p0) * rng.normal()
    xs = []
    for _ in range(T):
        x = a * x + np.sqrt(q) * rng.normal()
        xs.append(x)
    j = rng.choice(len(weights), size=T, p=weights)
    return np.array(xs), np.array(xs) + means[j] + np.sqrt(variances[j]) * rng.normal(size=T)


def test_single_component_equals_kalman():
    rng = np.random.default_rng(3)
    a, q, r, mu, m0, p0, T = 0.9, 0.5, 1.0, 0.2, 0.3, 2.0, 50
    xs, zs = _simulate(rng, a, q, m0, p0, T, [1.0], np.array([mu]), np.array([r]))
    zs[7] = np.nan
    exact = kalman_np.kalman_loglik(zs - mu, [[a]], [[1.0]], [[q]], [[r]], [m0], [[p0]])
    sd = max(np.sqrt(q / (1 - a * a)), np.sqrt(p0))
    L = 12 * sd
    assert np.abs(xs).max() < L / 2
    grid = np.linspace(-L, L, 4001)
    got = gm_noise_np.grid_loglik(zs, a, q, [1.0], [mu], [r], m0, p0, grid)
    np.testing.assert_allclose(got, exact, rtol=1e-6)
    # the Riemann sums of Gaussians converge spectrally: far coarser grids are already exact
    coarse = gm_noise_np.grid_loglik(zs, a, q, [1.0], [mu], [r], m0, p0, np.linspace(-L, L, 201))
    np.testing.assert_allclose(coarse, exact, rtol=1e-12)


def _kalman_loglik_varying(zs, a, q, m0, p0, offsets, rs):
    """Scalar Kalman log-likelihood with a per-step measurement offset and variance."""
    m, P, ll = m0, p0, 0.0
    for z, o, r in zip(zs, offsets, rs):
        m, P = a * m, a * a * P + q
        S = P + r
        e = z - m - o
        ll += -0.5 * (e * e / S + np.log(2 * np.pi * S))
        K = P / S
        m, P = m + K * e, (1 - K) * P
    return ll


def test_two_components_equals_enumerated_histories():
    rng = np.random.default_rng(4)
    a, q, m0, p0, T = 0.95, 0.3, -0.5, 1.0, 10
    xs, zs = _simulate(rng, a, q, m0, p0, T, W2, MU2, S2)
    terms = []
    for hist in itertools.product(range(2), repeat=T):
        j = np.array(hist)
        terms.append(np.log(W2[j]).sum() + _kalman_loglik_varying(zs, a, q, m0, p0, MU2[j], S2[j]))
    exact = logsumexp(terms)
    grid = np.linspace(-15.0, 15.0, 601)
    assert np.abs(xs).max() < 7.5
    got = gm_noise_np.grid_loglik(zs, a, q, W2, MU2, S2, m0, p0, grid)
    np.testing.assert_allclose(got, exact, rtol=1e-10)


def test_known_state_equals_iid_mixture():
    rng = np.random.default_rng(5)
    T = 200
    _, zs = _simulate(rng, 1.0, 0.0, 0.0, 0.0, T, W2, MU2, S2)  # x_k = 0
    iid = gm_noise_np.gm_logpdf(zs, W2, MU2, S2).sum()
    for grid in (np.linspace(-1.0, 1.0, 21), np.linspace(-10.0, 10.0, 2001)):
        got = gm_noise_np.grid_loglik(zs, 1.0, 1e-12, W2, MU2, S2, 0.0, 1e-12, grid)
        np.testing.assert_allclose(got, iid, rtol=1e-12)
    # the fit with the state known is the i.i.d. EM fit
    w0, mu0, s20 = [0.5, 0.5], [-1.0, 1.0], [1.0, 1.0]
    fit = gm_noise_np.ml_fit_grid(zs, 1.0, 1e-12, 0.0, 1e-12, np.linspace(-1.0, 1.0, 21), w0, mu0, s20)
    w, mu, s2, ll = gm_noise_np.em_iid(zs, w0, mu0, s20)
    order = np.argsort(mu)
    np.testing.assert_allclose(fit["loglik"], ll, rtol=1e-12)
    np.testing.assert_allclose(fit["weights"], w[order], atol=1e-7)
    np.testing.assert_allclose(fit["means"], mu[order], atol=1e-7)
    np.testing.assert_allclose(fit["variances"], s2[order], rtol=1e-7)
    assert np.all(np.abs(fit["grad"]) < 1e-6), fit["grad"]


def test_em_iid_recovers_mixture():
    rng = np.random.default_rng(6)
    N = 20000
    j = rng.choice(2, size=N, p=W2)
    x = MU2[j] + np.sqrt(S2[j]) * rng.normal(size=N)
    w, mu, s2, ll = gm_noise_np.em_iid(x, [0.5, 0.5], [-0.5, 0.5], [1.0, 1.0], iters=5000)
    order = np.argsort(mu)
    w, mu, s2 = w[order], mu[order], s2[order]
    # standard errors if the labels were seen (the mixture's overlap inflates them somewhat)
    se_w = np.sqrt(W2 * (1 - W2) / N)
    se_mu = np.sqrt(S2 / (N * W2))
    se_s2 = S2 * np.sqrt(2 / (N * W2))
    assert np.all(np.abs(w - W2) < 5 * se_w), (w, se_w)
    assert np.all(np.abs(mu - MU2) < 5 * se_mu), (mu, se_mu)
    assert np.all(np.abs(s2 - S2) < 5 * se_s2), (s2, se_s2)
    np.testing.assert_allclose(ll, gm_noise_np.gm_logpdf(x, w, mu, s2).sum(), rtol=1e-14)
    assert ll >= gm_noise_np.gm_logpdf(x, W2, MU2, S2).sum()
