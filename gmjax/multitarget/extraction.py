"""Multi-target state extraction from a PHD intensity: hard (Vo & Ma 2006, Table III) and relaxed.

:func:`extract` turns the posterior intensity into a padded set of target states
(:class:`Estimates`): every component with ``w > threshold`` gives ``round(w)`` copies of its mean.
:func:`soft_estimates` is its relaxation: every component's mean ``max_copies`` times with a smooth
existence weight per copy, the input of the relaxed GOSPA (:func:`gmjax.multitarget.metrics.soft_gospa`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp

from gmjax._types import Array
from gmjax.mixture import GaussianMixture
from gmjax.reduction.relax import soft_step, validate_mode

__all__ = ["Estimates", "extract", "soft_estimates"]


class Estimates(NamedTuple):
    """Extracted target states as a padded set.

    Attributes:
        states: ``(E, d)`` extracted means (0 in padded rows).
        mask: ``(E,)`` which rows are estimates.
        n_estimates: ``()`` int32, the number extracted before padding (may exceed ``E``: then
            ``overflow``).
        overflow: ``()`` bool, more estimates than ``E`` (the heaviest components come first).
    """

    states: Array
    mask: Array
    n_estimates: Array
    overflow: Array


def extract(intensity: GaussianMixture, threshold: Any = 0.5, *, max_estimates: int) -> Estimates:
    """Multi-target state extraction (Vo & Ma 2006, Table III).

    Every component with ``w > threshold`` contributes ``n = #{r >= 0 : w > r + threshold}`` copies of
    its mean (``round(w)`` for ``threshold = 0.5``, ties rounded down), heaviest components first.

    Args:
        intensity: the posterior intensity, capacity ``J``.
        threshold: ``()`` the extraction threshold (may be traced).
        max_estimates: static ``E``, the capacity of the estimate set.
    """
    w = jnp.where(intensity.mask, intensity.weights, 0.0)
    thr = jnp.asarray(threshold, w.dtype)
    copies = jnp.where(w > thr, jnp.ceil(w - thr), 0.0).astype(jnp.int32)
    order = jnp.argsort(-w, stable=True)
    copies_o = copies[order]
    ends = jnp.cumsum(copies_o)
    count = ends[-1]
    slot = jnp.arange(max_estimates)
    which = jnp.searchsorted(ends, slot, side="right")
    mask = slot < count
    comp = order[jnp.minimum(which, intensity.capacity - 1)]
    states = jnp.where(mask[:, None], intensity.means[comp], 0.0)
    return Estimates(states, mask, count, count > max_estimates)


def soft_estimates(
    intensity: GaussianMixture,
    threshold: Any = 0.5,
    temperature: Any = 0.0,
    *,
    max_copies: int = 2,
    mode: str = "soft",
) -> tuple[Array, Array]:
    """Relaxed state extraction: every component's mean ``max_copies`` times with existence weights.

    Copy ``r`` of component ``j`` exists with weight ``sigma((w_j - r - threshold) / T)``; with
    ``T = 0`` the weights are exactly the 0/1 decisions of :func:`extract` (``w > r + threshold``), up
    to ``max_copies`` copies per component. Feed the result to
    :func:`gmjax.multitarget.metrics.soft_gospa`.

    Returns:
        ``(candidates (J max_copies, d), existence (J max_copies,))``.
    """
    validate_mode(mode)
    w = jnp.where(intensity.mask, intensity.weights, 0.0)
    r = jnp.arange(max_copies, dtype=w.dtype)
    thr = jnp.asarray(threshold, w.dtype)
    e = soft_step(w[:, None] - r[None, :] - thr, temperature, mode=mode, strict=True)
    e = jnp.where(intensity.mask[:, None], e, 0.0)
    cand = jnp.repeat(intensity.means, max_copies, axis=0)
    return cand, e.reshape(-1)
