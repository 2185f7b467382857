"""Shape checks at every public entry that takes points or two mixtures (issue 15, item 4).

Each case used to return a silently wrong number (or crash deep inside XLA); now it raises a
``ValueError`` that names the argument. The well-shaped calls next to them still work and agree with
an independent computation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from gmjax import GaussianMixture, gaussian, metrics
from gmjax import filters as F
from gmjax import mixture as mx

G1 = GaussianMixture.create([0.3, 0.7], [-1.0, 2.0], [1.0, 0.5])
G2 = GaussianMixture.create([1.0], [[0.0, 0.0]], [np.eye(2)], capacity=2)


def _ref_pdf_1d(x):
    return 0.3 * stats.norm.pdf(x, -1.0, 1.0) + 0.7 * stats.norm.pdf(x, 2.0, np.sqrt(0.5))


def test_pdf_of_a_1d_mixture_refuses_an_ambiguous_vector_and_takes_points_as_n_by_1():
    # x of shape (2,) returned the density at the first point only
    with pytest.raises(
        ValueError, match=r"x: expected one point \(1,\) or points \(n, 1\).*pass shape \(2, 1\)"
    ):
        mx.pdf(G1, jnp.asarray([0.0, 1.0]))
    with pytest.raises(ValueError, match=r"x: expected"):
        jax.jit(mx.logpdf)(G1, jnp.asarray([0.0, 1.0]))  # a static check: also under jit
    pts = np.array([0.0, 1.0, 2.5])
    np.testing.assert_allclose(np.asarray(mx.pdf(G1, pts[:, None])), _ref_pdf_1d(pts), rtol=1e-12)
    np.testing.assert_allclose(float(mx.pdf(G1, pts[1:2])), _ref_pdf_1d(1.0), rtol=1e-12)
    with pytest.raises(
        ValueError, match=r"x: expected one point \(2,\) or points \(n, 2\).*got shape \(3,\)"
    ):
        mx.logpdf(G2, jnp.zeros(3))
    with pytest.raises(ValueError, match=r"x: expected"):
        mx.component_logpdfs(G2, jnp.zeros((4, 2, 1)))


def test_two_mixtures_of_different_dimensions_are_refused():
    for f in (metrics.ise, metrics.nise, metrics.l2_inner, metrics.cross_overlap, mx.concat):
        with pytest.raises(
            ValueError, match=r"a, b: mixtures of different dimensions \(a is 1-D, b is 2-D\)"
        ):
            f(G1, G2)
    with pytest.raises(ValueError, match=r"a, b: mixtures of different dimensions"):
        metrics.kl_mc(G1, G2, jax.random.key(0), 10)
    # same dimension: the closed form of two 1-D Gaussians, int N1 N2 = N(m1; m2, P1 + P2)
    a = GaussianMixture.create([1.0], [0.0], [1.0])
    b = GaussianMixture.create([1.0], [1.0], [2.0])
    np.testing.assert_allclose(
        float(metrics.l2_inner(a, b)), stats.norm.pdf(0.0, 1.0, np.sqrt(3.0)), rtol=1e-12
    )


def test_marginal_affine_and_gaussian_helpers_name_the_argument():
    with pytest.raises(ValueError, match=r"dims: \[5\] out of range for a 2-D mixture"):
        mx.marginal(G2, [5])  # clamped to the last dimension before
    with pytest.raises(ValueError, match=r"dims: repeated dimension"):
        mx.marginal(G2, [0, 0])
    with pytest.raises(ValueError, match=r"dims: expected a non-empty sequence of integers"):
        mx.marginal(G2, [])
    np.testing.assert_array_equal(np.asarray(mx.marginal(G2, [-1]).means), np.asarray(G2.means[:, 1:]))
    with pytest.raises(ValueError, match=r"A: expected shape \(e, 2\)"):
        mx.affine(G2, jnp.eye(3))
    with pytest.raises(ValueError, match=r"b: expected shape \(2,\)"):
        mx.affine(G2, jnp.eye(2), jnp.zeros(3))
    with pytest.raises(ValueError, match=r"dimension mismatch: x has d=2, mean has d=3"):
        gaussian.logpdf(jnp.zeros(2), jnp.zeros(3), jnp.eye(3))
    with pytest.raises(ValueError, match=r"cov: expected a square"):
        gaussian.mahalanobis_sq(jnp.zeros(2), jnp.zeros(2), jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"dimension mismatch"):
        gaussian.kl_divergence(jnp.zeros(2), jnp.eye(2), jnp.zeros(1), jnp.eye(1))
    with pytest.raises(ValueError, match=r"estimates, truths: expected \(\.\.\., d\) arrays with the same d"):
        metrics.rmse(jnp.zeros((5, 2)), jnp.zeros((5, 3)))
    with pytest.raises(ValueError, match=r"covs: expected shape \(5, 2, 2\)"):
        metrics.nees(jnp.zeros((5, 2)), jnp.zeros((5, 3, 3)), jnp.zeros((5, 2)))


def test_run_refuses_measurements_of_the_wrong_dimension_naming_zs():
    kf = F.kalman_filter(np.eye(2), np.array([[1.0, 0.0]]), np.eye(2), np.eye(1), np.zeros(2), np.eye(2))
    with pytest.raises(
        ValueError, match=r"zs: the filter's model measures m=1 values per step, but zs has shape \(4, 2\)"
    ):
        F.run(kf, jnp.zeros((4, 2)))
    model = mx.from_gaussian(jnp.zeros(2), jnp.eye(2))
    from gmjax.models import StateSpaceModel

    ssm = StateSpaceModel(
        lambda x, t: x, lambda x, t: x[:1], model, GaussianMixture.create([1.0], [0.0], [1.0]), model
    )
    for filt in (F.build_kf(ssm), F.build_imm([ssm, ssm], [[0.9, 0.1], [0.1, 0.9]], filter="kf")):
        with pytest.raises(ValueError, match=r"zs: the filter's model measures m=1"):
            F.run(filt, jnp.zeros((4, 3)))
        _, infos = F.run(filt, jnp.zeros((4, 1)))
        assert infos.mean.shape == (4, 2)
    assert F.base.measurement_dim(object()) is None  # params that do not say: no check
