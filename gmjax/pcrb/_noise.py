"""Fisher information of an additive noise density, Gaussian or Gaussian mixture.

For ``x_{n+1} = f(x_n) + w_n`` with ``w_n ~ p_w`` independent of ``x_n`` (and likewise
``z_n = h(x_n) + v_n``), the expectations of eqs 5-8 of seed 002 keep their Gaussian form with
``Q^{-1}`` replaced by the information of the noise's location,
``I_w = E[s(w) s(w)^T]``, ``s(w) = grad log p_w(w)``: ``D11 = E[F^T I_w F]``,
``D12 = -E[F]^T I_w``, ``D22 = I_w + E[H^T I_v H]`` (the terms with second derivatives of ``f``
and ``h`` vanish because ``E[s(w)] = 0``). For one Gaussian ``I_w = Q^{-1}``; for a mixture
``sum_j pi_j N(mu_j, Sigma_j)`` it has no closed form and is the mixture of per-component
expectations. Each is a tensor trapezoidal rule in the component's whitened coordinates (spectrally
accurate for smooth integrands under a Gaussian weight; Gauss-Hermite converges slowly here because
the score switches between components) for ``d <= 3``, and a fixed-seed Monte Carlo average beyond
(:func:`noise_information`).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import gaussian
from gmjax import mixture as gmm
from gmjax._types import Array, ArrayLike
from gmjax.mixture import GaussianMixture

__all__ = ["noise_information", "whitened_rule", "is_single_gaussian"]

_TRAPEZOID_POINTS = {1: 2001, 2: 301, 3: 81}
_HALF_WIDTH = 10.0
_MC_SAMPLES = 200_000


def whitened_rule(d: int, n_points: int | None = None, dtype: Any = None) -> tuple[Array, Array]:
    """Points ``(n, d)`` and weights ``(n,)`` for ``E[g(z)]``, ``z ~ N(0, I_d)``.

    A tensor trapezoidal rule on ``[-10, 10]^d`` with ``n_points`` per axis (default 2001, 301, 81
    for ``d = 1, 2, 3``), weights ``phi(z) h^d`` renormalised; for ``d > 3`` (or ``n_points=0``)
    200 000 standard-normal draws with a fixed seed.
    """
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    n = _TRAPEZOID_POINTS.get(d, 0) if n_points is None else int(n_points)
    if n <= 0:
        draws = jax.random.normal(jax.random.PRNGKey(0), (_MC_SAMPLES, d), dtype)
        return draws, jnp.full((_MC_SAMPLES,), 1.0 / _MC_SAMPLES, dtype)
    g = np.linspace(-_HALF_WIDTH, _HALF_WIDTH, n)
    grids = np.meshgrid(*([g] * d), indexing="ij")
    z = np.stack([a.ravel() for a in grids], axis=1)
    w = np.exp(-0.5 * np.sum(z * z, axis=1))
    return jnp.asarray(z, dtype), jnp.asarray(w / w.sum(), dtype)


def is_single_gaussian(noise) -> bool:
    """True for an array covariance or a mixture with one live component (eagerly known)."""
    if not isinstance(noise, GaussianMixture):
        return True
    mask = noise.mask
    if isinstance(mask, jax.core.Tracer):
        return noise.capacity == 1
    return int(np.asarray(mask).sum()) == 1


def _inv_pd(M: Array) -> Array:
    M = gaussian.symmetrize(M)
    L = jnp.linalg.cholesky(M)
    return gaussian.symmetrize(jax.scipy.linalg.cho_solve((L, True), jnp.eye(M.shape[-1], dtype=M.dtype)))


def noise_information(
    noise: ArrayLike | GaussianMixture, n_points: int | None = None, dtype: Any = None
) -> Array:
    """``I = E[grad log p(w) grad log p(w)^T]`` ``(d, d)`` of a noise density.

    Args:
        noise: a covariance ``(d, d)`` (``I = Q^{-1}``), or a :class:`GaussianMixture` (one live
            component: its inverse covariance; several: :func:`whitened_rule` per component).
        n_points: trapezoid points per axis for a mixture (default: see :func:`whitened_rule`).
        dtype: result dtype (default the noise's).

    Returns:
        ``(d, d)`` symmetric positive definite information matrix.
    """
    if not isinstance(noise, GaussianMixture):
        M = jnp.asarray(noise, dtype)
        return _inv_pd(M)
    dtype = noise.means.dtype if dtype is None else dtype
    gm = GaussianMixture(*(jnp.asarray(a, dtype) if a.dtype != bool else a for a in noise))
    gm = gmm.normalize(gm)
    d = gm.dim
    if is_single_gaussian(gm):
        k = jnp.argmax(gm.mask)
        return _inv_pd(gm.covs[k])
    points, weights = whitened_rule(d, n_points, dtype)
    score = jax.vmap(jax.grad(lambda w: gmm.logpdf(gm, w)))

    def per_component(mean, cov):
        L = jnp.linalg.cholesky(gaussian.symmetrize(cov))
        S = score(mean + points @ L.T)
        return jnp.einsum("n,ni,nj->ij", weights, S, S)

    per = jax.vmap(per_component)(gm.means, gm.covs)
    return gaussian.symmetrize(jnp.einsum("k,kij->ij", gm.weights, per))
