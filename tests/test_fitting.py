"""gmjax.fitting (issue 45, partial): a Kalman filter's noise variances learned by maximum likelihood
equal the exact-likelihood optimum of benchmarks/reference/kalman_np.py (scipy.optimize) to 1e-6."""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from gmjax import filters, fitting

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from reference import kalman_np  # noqa: E402


def test_kf_noise_variances_equal_the_exact_ml_optimum():
    F, H, m0, P0 = np.array([[0.95]]), np.array([[1.0]]), np.zeros(1), 4.0 * np.eye(1)
    rng = np.random.default_rng(0)
    zs = np.empty((3, 80, 1))
    for b in range(3):
        x = rng.normal(0, 2, 1)
        for t in range(80):
            x = F @ x + rng.normal(0, np.sqrt(0.3), 1)
            zs[b, t] = H @ x + rng.normal(0, np.sqrt(1.5), 1)
    q, r, _ = kalman_np.ml_noise_variances(zs, F, H, m0, P0, 1.0, 1.0, np.eye(1), np.eye(1))
    kf = filters.kalman_filter(F, H, np.eye(1), np.eye(1), m0, P0)
    res = fitting.fit(kf, zs, fit=["Q", "R"], key=jax.random.key(0), progress=False)
    assert res.converged
    np.testing.assert_allclose([res.values["Q"][0, 0], res.values["R"][0, 0]], [q, r], rtol=1e-6)


def test_bad_leaf_names_are_refused_listing_the_leaves():
    kf = filters.kalman_filter(np.eye(1), np.eye(1), np.eye(1), np.eye(1), np.zeros(1), np.eye(1))
    with pytest.raises(ValueError, match=r"^fit: 'model.Q' names no floating leaf .* the leaves are \['F'"):
        fitting.fit(kf, np.zeros((5, 1)), fit="model.Q", key=jax.random.key(0), progress=False)
