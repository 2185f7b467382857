"""gmjax.reduction.eise.ise: soft and one-hot cluster merges and the closed-form EISE (seed 000 eqs 29-35,
seed 003 eq 10) against numerical integration and the NumPy reference."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from eise_cases import CASES, K, case, case_np, random_gm
from scipy.stats import multivariate_normal, norm

from gmjax.mixture import moments
from gmjax.reduction.clustering import gauss_cluster
from gmjax.reduction.eise import (
    cluster_ise,
    hard_eise,
    merge_membership,
    onehot_membership,
)
from gmjax.reduction.merge import merge_labels
from references import pcm_numpy as ref


@pytest.mark.parametrize("method", ["ci", "moment"])
def test_merge_membership_matches_merge_labels_and_reference(method):
    gm, w, m, P = random_gm(0, d=2)
    labels = gauss_cluster(gm, 3.0).labels
    mine = merge_membership(gm, onehot_membership(labels, K, gm.dtype), method)
    theirs = merge_labels(gm, labels, K, method)
    for a, b in zip(mine, theirs):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    fn = ref.merge_ci if method == "ci" else ref.merge_moment
    for c in np.unique(np.asarray(labels)[: len(w)]):
        idx = np.flatnonzero(np.asarray(labels) == c)
        W, mb, Pb = fn(w[idx], m[idx], P[idx])
        np.testing.assert_allclose(mine.weights[c], W, rtol=1e-12)
        np.testing.assert_allclose(mine.means[c], mb, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(mine.covs[c], Pb, rtol=1e-10, atol=1e-12)
    assert float(jnp.sum(mine.weights)) == pytest.approx(1.0, rel=1e-14)


def test_moment_merge_preserves_mixture_moments_with_soft_memberships():
    gm, *_ = random_gm(1, d=2)
    A = jax.nn.softmax(jax.random.normal(jax.random.PRNGKey(0), (K, 4)), axis=1)
    merged = merge_membership(gm, A, "moment")
    for a, b in zip(moments(merged), moments(gm)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)


def _weighted_pdfs_1d(gm, x):
    """``(n, K)`` ``w_k N(x; m_k, P_k)`` by SciPy (0 on padded slots)."""
    mu = np.asarray(gm.means)[:, 0]
    sd = np.sqrt(np.asarray(gm.covs)[:, 0, 0])
    w = np.asarray(gm.weights) * np.asarray(gm.mask)
    return norm.pdf(x[:, None], mu[None, :], sd[None, :]) * w[None, :]


def _grid_ise_1d(gm, A, merged):
    x = np.linspace(-25, 30, 40001)
    f = _weighted_pdfs_1d(gm, x) @ np.asarray(A)  # (n, C) cluster sub-mixtures
    q = _weighted_pdfs_1d(merged, x)  # (n, C) merged components
    return np.trapezoid((f - q) ** 2, x, axis=0)


@pytest.mark.parametrize("method", ["ci", "moment"])
def test_cluster_ise_equals_numerical_integration_1d(method):
    gm = case("multimodal")
    labels = gauss_cluster(gm, 3.0).labels
    A = onehot_membership(labels, K, gm.dtype)
    merged = merge_membership(gm, A, method)
    closed = np.asarray(cluster_ise(gm, A, merged))
    np.testing.assert_allclose(closed, _grid_ise_1d(gm, A, merged), rtol=1e-7, atol=1e-12)
    assert np.count_nonzero(closed > 1e-8) >= 1  # some cluster really merged
    # soft memberships too (the relaxation uses the same formula)
    A_soft = jax.nn.softmax(jax.random.normal(jax.random.PRNGKey(1), (K, K)), axis=1)
    merged_s = merge_membership(gm, A_soft, method)
    np.testing.assert_allclose(
        cluster_ise(gm, A_soft, merged_s), _grid_ise_1d(gm, A_soft, merged_s), rtol=1e-7, atol=1e-12
    )


def test_cluster_ise_equals_numerical_integration_2d():
    gm, *_ = random_gm(2, n=6, d=2)
    labels = gauss_cluster(gm, 4.0).labels
    A = onehot_membership(labels, K, gm.dtype)
    merged = merge_membership(gm, A, "ci")
    closed = np.asarray(cluster_ise(gm, A, merged))
    g = np.linspace(-9, 11, 601)
    X = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    h = (g[1] - g[0]) ** 2

    def wpdfs(g):
        return np.stack(
            [
                multivariate_normal(np.asarray(g.means[k]), np.asarray(g.covs[k])).pdf(X)
                * float(g.weights[k] * g.mask[k])
                for k in range(g.capacity)
            ],
            axis=1,
        )

    comp, qcomp = wpdfs(gm), wpdfs(merged)
    numeric = ((comp @ np.asarray(A) - qcomp) ** 2).sum(0) * h
    np.testing.assert_allclose(closed, numeric, rtol=1e-6, atol=1e-12)
    assert closed.max() > 1e-6


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("seed000", [True, False])
def test_hard_eise_matches_reference(name, seed000):
    gm = case(name)
    w, m, P = case_np(name)
    opts = (
        dict(method="ci", regularizer="exp", ise_scale=0.5, triangular=False, rule="split")
        if seed000
        else dict(method="moment", regularizer="log10", ise_scale=1.0, triangular=True, rule="absorb")
    )
    for lam in (1.0, 2.0, 3.0, 4.0):
        labels = gauss_cluster(gm, lam, triangular=opts["triangular"], subset_rule=opts["rule"]).labels
        e, merged, n = hard_eise(
            gm,
            labels,
            alpha=0.01,
            method=opts["method"],
            regularizer=opts["regularizer"],
            ise_scale=opts["ise_scale"],
        )
        *_, clusters, e_ref = ref.reduce_fixed(
            w,
            m,
            P,
            lam,
            merge=opts["method"],
            triangular=opts["triangular"],
            subset_rule=opts["rule"],
            alpha=0.01,
            reg=opts["regularizer"],
            ise_scale=opts["ise_scale"],
        )
        assert float(e) == pytest.approx(e_ref, rel=1e-10, abs=1e-15)
        assert int(n) == len(clusters)
