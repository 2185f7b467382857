"""gmjax.reduction.merge: moment and covariance-intersection merges against their equations and SciPy,
merging by labels against per-cluster merges, and its gradients with empty clusters."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_reduction_utils import scatter_padding

from gmjax import reduction as R
from gmjax.metrics import ise as _ise_eager
from gmjax.mixture import moments

ise = jax.jit(_ise_eager)

from test_reduction_utils import seeded_mixture


@pytest.mark.parametrize("d", [1, 3])
def test_merge_moment_preserves_moments(d):
    gm, (w, m, P) = seeded_mixture(0, n=9, d=d, capacity=12)
    W, mu, C = R.merge_moment(gm)
    mu_ref, C_ref = moments(gm)
    assert abs(float(W) - w.sum()) < 1e-14
    np.testing.assert_allclose(np.asarray(mu), np.asarray(mu_ref), atol=1e-12)
    np.testing.assert_allclose(np.asarray(C), np.asarray(C_ref), atol=1e-12)
    # eq 72 (raw second moment) written out in NumPy
    wn = w / w.sum()
    mu_np = wn @ m
    C_np = np.einsum("k,kij->ij", wn, P + np.einsum("ki,kj->kij", m, m)) - np.outer(mu_np, mu_np)
    np.testing.assert_allclose(np.asarray(C), C_np, atol=1e-12)
    # unnormalised weights: merged weight is their sum, moments unchanged
    W2, mu2, C2 = R.merge_moment(gm._replace(weights=3.0 * gm.weights))
    assert abs(float(W2) - 3 * w.sum()) < 1e-13
    np.testing.assert_allclose(np.asarray(mu2), np.asarray(mu), atol=1e-12)
    # padding positions do not matter
    W3, mu3, C3 = R.merge_moment(scatter_padding(gm, 20, seed=1))
    np.testing.assert_allclose(np.asarray(C3), np.asarray(C), atol=1e-13)


def test_merge_ci_matches_equations():
    gm, (w, m, P) = seeded_mixture(1, n=5, d=2, capacity=7)
    W, mu, C = R.merge_ci(gm)
    wn = w / w.sum()
    info = sum(wn[k] * np.linalg.inv(P[k]) for k in range(5))  # eq 38
    C_ref = np.linalg.inv(info)
    mu_ref = C_ref @ sum(wn[k] * np.linalg.solve(P[k], m[k]) for k in range(5))  # eq 39
    assert abs(float(W) - w.sum()) < 1e-14
    np.testing.assert_allclose(np.asarray(C), C_ref, atol=1e-12)
    np.testing.assert_allclose(np.asarray(mu), mu_ref, atol=1e-12)


def test_merge_ci_optimized_matches_scipy():
    """Eq 40 (trace of the eq-38 covariance) minimised on the simplex: our projected steps reach
    SciPy's SLSQP optimum."""
    from scipy.optimize import minimize

    gm, (w, m, P) = seeded_mixture(2, n=5, d=2, capacity=6)
    Pi = np.linalg.inv(P)

    def f(lam):
        return np.trace(np.linalg.inv(np.einsum("k,kij->ij", lam, Pi)))

    res = minimize(
        f,
        w / w.sum(),
        method="SLSQP",
        bounds=[(0, 1)] * 5,
        constraints=[{"type": "eq", "fun": lambda x: x.sum() - 1}],
        options={"ftol": 1e-15, "maxiter": 1000},
    )
    _, _, C = R.merge_ci(gm, optimize=True, n_steps=30)
    assert np.trace(np.asarray(C)) <= f(w / w.sum())
    np.testing.assert_allclose(np.trace(np.asarray(C)), res.fun, rtol=1e-6)


@pytest.mark.parametrize("method", ["moment", "ci"])
def test_merge_labels_equals_per_cluster_merge(method):
    gm, _ = seeded_mixture(3, n=9, d=2, capacity=11)
    gm = scatter_padding(gm, 14, seed=3)
    labels = jnp.asarray([0, 2, 1, 0, -1, 2, 2, 0, 1, 1, 0, 2, 0, 1])
    out = R.merge_labels(gm, labels, 4, method)
    merge = R.merge_moment if method == "moment" else R.merge_ci
    lab = np.where(np.asarray(gm.mask), np.asarray(labels), -1)
    for c in range(4):
        sel = jnp.asarray(lab == c)
        if not sel.any():
            assert not bool(out.mask[c]) and float(out.weights[c]) == 0.0
            continue
        W, mu, C = merge(gm._replace(mask=gm.mask & sel))
        assert bool(out.mask[c])
        np.testing.assert_allclose(float(out.weights[c]), float(W), atol=1e-14)
        np.testing.assert_allclose(np.asarray(out.means[c]), np.asarray(mu), atol=1e-12)
        np.testing.assert_allclose(np.asarray(out.covs[c]), np.asarray(C), atol=1e-12)
    dropped = float(jnp.sum(jnp.where(gm.mask & (labels < 0), gm.weights, 0.0)))
    assert abs(float(jnp.sum(out.weights)) + dropped - float(jnp.sum(gm.weights))) < 1e-14


def test_merge_labels_gradients_finite_with_empty_clusters():
    gm, _ = seeded_mixture(4, n=4, d=2, capacity=6)
    labels = jnp.asarray([0, 0, 2, 2, 1, 3])  # slots 4, 5 padded -> clusters 1, 3 empty

    def f(means):
        out = R.merge_labels(gm._replace(means=means), labels, 4, "ci", optimize=True)
        return jnp.sum(out.covs) + jnp.sum(out.means**2)

    g = jax.grad(f)(gm.means)
    assert np.isfinite(np.asarray(g)).all()
