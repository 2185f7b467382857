"""True-noise samplers used by the scenarios (they may differ from the mixtures the filters assume)."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from gmjax import mixture as gmm
from gmjax._types import Array, ArrayLike, PRNGKey
from gmjax.mixture import GaussianMixture

__all__ = ["glint", "glint_variance", "mixture_sampler", "laplace"]


def laplace(key: PRNGKey, loc: ArrayLike, scale: ArrayLike, shape: tuple[int, ...] = ()) -> Array:
    """Laplace samples with density ``exp(-|x - loc| / scale) / (2 scale)`` (variance ``2 scale^2``)."""
    loc = jnp.asarray(loc)
    scale = jnp.asarray(scale)
    shape = shape or jnp.broadcast_shapes(loc.shape, scale.shape)
    return loc + scale * jax.random.laplace(key, shape, dtype=jnp.result_type(loc, scale, float))


def glint(
    key: PRNGKey,
    loc: ArrayLike,
    gauss_std: ArrayLike,
    laplace_scale: ArrayLike,
    frequency: float,
) -> Array:
    """One glint-noise draw (seed 000 eqs 46–47): ``(1 - eps) N(loc, gauss_std^2) + eps Laplace(loc, eta)``.

    Each component of a vector draw switches independently with probability ``frequency``. The draw
    has ``loc``'s floating dtype.
    """
    loc = jnp.asarray(loc)
    if not jnp.issubdtype(loc.dtype, jnp.floating):
        loc = loc.astype(float)
    dtype = loc.dtype  # the draw has loc's dtype (a float32 scenario stays float32 under x64)
    gauss_std, laplace_scale = jnp.asarray(gauss_std, dtype), jnp.asarray(laplace_scale, dtype)
    shape = jnp.broadcast_shapes(loc.shape, gauss_std.shape, laplace_scale.shape)
    k_switch, k_gauss, k_lap = jax.random.split(key, 3)
    gauss = loc + gauss_std * jax.random.normal(k_gauss, shape, dtype)
    lap = laplace(k_lap, loc, laplace_scale, shape)
    use_laplace = jax.random.uniform(k_switch, shape, dtype) < frequency
    return jnp.where(use_laplace, lap, gauss)


def glint_variance(gauss_std: ArrayLike, laplace_scale: ArrayLike, frequency: float) -> Array:
    """Variance of :func:`glint`: ``(1 - eps) sigma^2 + eps 2 eta^2``."""
    return (1 - frequency) * jnp.asarray(gauss_std) ** 2 + frequency * 2 * jnp.asarray(laplace_scale) ** 2


def mixture_sampler(gm: GaussianMixture) -> Callable[..., Array]:
    """``(key, t) -> (d,)``: one draw from a Gaussian mixture (time-invariant)."""

    def sample(key: PRNGKey, t: Array | None = None) -> Array:
        del t
        return gmm.sample(gm, key, 1)[0]

    return sample
