"""Threshold pruning and Mahalanobis merging of the GM-PHD filter (Vo & Ma 2006, Table II)."""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp

from gmjax import _validate, gaussian
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction.base import ReductionInfo, Stateless, make_info
from gmjax.reduction.merge import merge_labels
from gmjax.reduction.prune import _keep

__all__ = ["vo_ma", "VoMa"]


@partial(jax.jit, static_argnames=("max_components", "capacity"))
def _vo_ma(gm, prune_threshold, merge_threshold, max_components, capacity):
    K = gm.capacity
    w = jnp.where(gm.mask, gm.weights, 0.0)
    total = jnp.sum(w)
    alive = gm.mask & (w > prune_threshold)
    heaviest = jnp.argmax(jnp.where(gm.mask, w, -jnp.inf))
    alive = jnp.where(jnp.any(alive), alive, jnp.arange(K) == heaviest)
    pruned = total - jnp.sum(jnp.where(alive, w, 0.0))
    covs = gm.covs

    def body(step, carry):
        alive, labels = carry
        any_alive = jnp.any(alive)
        j = jnp.argmax(jnp.where(alive, w, -jnp.inf))
        # (m_i - m_j)^T P_i^{-1} (m_i - m_j) <= U, with the candidate's own covariance P_i
        dist = gaussian.spd_inv_quad(gm.means - gm.means[j], covs)
        L = alive & (dist <= merge_threshold) & any_alive
        return alive & ~L, jnp.where(L, step, labels)

    _, labels = jax.lax.fori_loop(0, K, body, (alive, jnp.full(K, -1, jnp.int32)))
    merged = merge_labels(gm, labels, K, "moment")
    # cap at J_max: keep the heaviest merged components, then renormalise to the input's total
    J = K if max_components is None else max_components
    work = merged._replace(weights=merged.weights)
    out, info = _keep(work, merged.mask, min(J, K))
    kept_labels = jnp.where(labels >= 0, info.labels[jnp.maximum(labels, 0)], -1)
    out_total = jnp.sum(out.weights)
    scale = jnp.where(out_total > 0, total / jnp.where(out_total > 0, out_total, 1.0), 1.0)
    out = out._replace(weights=out.weights * scale)
    out, labels_f, overflow, dropped = _util.finalize(gm, out, kept_labels, capacity)
    return out, make_info(
        gm, out, labels_f, pruned_mass=pruned + info.pruned_mass, overflow=overflow | info.overflow
    )


@_util.guard_nan(prune_threshold=1e-5, merge_threshold=4.0)
def vo_ma(
    gm: GaussianMixture,
    prune_threshold: Any = 1e-5,
    merge_threshold: Any = 4.0,
    max_components: int | None = None,
    *,
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """GM-PHD pruning and merging (Vo & Ma 2006, IEEE TSP 54(11), Table II; Stone Soup's
    ``GaussianMixtureReducer``).

    Discard components with ``w <= T`` (``prune_threshold``); then, until none is left, take the
    heaviest remaining ``j``, merge every remaining ``i`` with
    ``(m_i - m_j)^T P_i^{-1} (m_i - m_j) <= U`` (``merge_threshold``) moment-preservingly, and
    remove them; finally keep the ``J_max`` (``max_components``) heaviest. Unlike a PHD intensity,
    the result is rescaled to the input's total weight (docs/design.md §2: mixtures are returned normalised);
    ``info.pruned_mass`` is the weight removed before rescaling.

    Args:
        gm: input mixture, capacity ``K``.
        prune_threshold, merge_threshold: non-negative, may be traced.
        max_components: static ``J_max`` (default ``K``).
        capacity: static output capacity (default ``K``).
        key: unused.
    """
    del key
    _validate.validate_mixture(gm)
    _validate.validate_nonneg(prune_threshold, "prune_threshold")
    _validate.validate_nonneg(merge_threshold, "merge_threshold")
    if max_components is not None:
        max_components = _validate.validate_count(max_components, "max_components", 1, gm.capacity)
    cap = _validate.validate_capacity(capacity, gm)
    dt = gm.weights.dtype
    return _vo_ma(gm, jnp.asarray(prune_threshold, dt), jnp.asarray(merge_threshold, dt), max_components, cap)


@pytree_dataclass
class VoMa(Stateless):
    """Reducer config for :func:`vo_ma` (thresholds dynamic)."""

    prune_threshold: Any = 1e-5
    merge_threshold: Any = 4.0
    max_components: int | None = static_field(None)
    capacity: int | None = static_field(None)

    def __call__(
        self, gm: GaussianMixture, *, key: Array | None = None
    ) -> tuple[GaussianMixture, ReductionInfo]:
        return vo_ma(
            gm,
            self.prune_threshold,
            self.merge_threshold,
            self.max_components,
            capacity=self.capacity,
            key=key,
        )
