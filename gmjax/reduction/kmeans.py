"""GMM k-means coarsening (seed 002 eq 69, Algorithm 3, moment-preserving merge eqs 70–72)."""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from gmjax import _validate, gaussian
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction.base import ReductionInfo, Stateless, calls, make_info
from gmjax.reduction.merge import merge_labels

__all__ = ["kmeans", "KMeans", "weighted_mahalanobis_sq", "farthest_point_init"]


def weighted_mahalanobis_sq(wi: Array, mi: Array, Pi: Array, wj: Array, mj: Array, Pj: Array) -> Array:
    """Weighted Mahalanobis distance between two components (seed 002 eq 69), broadcasting.

    ``d_ij^2 = w_i w_j / (w_i + w_j) (mu_i - mu_j)^T (Sigma_i + Sigma_j)^{-1} (mu_i - mu_j)``;
    0 when ``w_i + w_j = 0``.
    """
    s = wi + wj
    ok = s > 0
    coef = jnp.where(ok, wi * wj / jnp.where(ok, s, 1.0), 0.0)
    return coef * gaussian.spd_inv_quad(mi - mj, Pi + Pj)


def _dist_to_centers(gm: GaussianMixture, cw, cm, cP):
    """``(K, C)`` eq-69 distances between every slot of ``gm`` and every center."""
    w = jnp.where(gm.mask, gm.weights, 0.0)
    return weighted_mahalanobis_sq(
        w[:, None], gm.means[:, None, :], gm.covs[:, None], cw[None, :], cm[None], cP[None]
    )


def farthest_point_init(gm: GaussianMixture, num_out: int) -> jax.Array:
    """Algorithm 3's initialisation: the heaviest component, then repeatedly the component whose
    eq-69 distance to its nearest chosen center is largest (ties: lowest slot index).

    Returns:
        ``(num_out,)`` int32 slot indices of the initial centers (if fewer than ``num_out`` slots
        are live, the tail repeats already-chosen slots; callers pass such mixtures through).
    """
    w = jnp.where(gm.mask, gm.weights, 0.0)
    first = jnp.argmax(jnp.where(gm.mask, w, -jnp.inf)).astype(jnp.int32)

    def dist_to(k):
        return weighted_mahalanobis_sq(w, gm.means, gm.covs, w[k], gm.means[k], gm.covs[k])

    def body(i, carry):
        idx, mind = carry
        k = jnp.argmax(jnp.where(gm.mask, mind, -jnp.inf)).astype(jnp.int32)
        return idx.at[i].set(k), jnp.minimum(mind, dist_to(k))

    idx0 = jnp.zeros(num_out, jnp.int32).at[0].set(first)
    idx, _ = jax.lax.fori_loop(1, num_out, body, (idx0, dist_to(first)))
    return idx


class _KState(NamedTuple):
    cw: jax.Array
    cm: jax.Array
    cP: jax.Array
    labels: jax.Array
    it: jax.Array
    done: jax.Array


def _assign(gm, cw, cm, cP):
    D = _dist_to_centers(gm, cw, cm, cP)
    lab = jnp.argmin(D, axis=1).astype(jnp.int32)
    return jnp.where(gm.mask, lab, -1)


@partial(jax.jit, static_argnames=("num_out", "max_iter", "tol", "capacity"))
def _kmeans(gm, num_out, max_iter, tol, capacity):
    init = farthest_point_init(gm, num_out)
    w = jnp.where(gm.mask, gm.weights, 0.0)
    s0 = _KState(
        w[init],
        gm.means[init],
        gm.covs[init],
        jnp.full(gm.capacity, -1, jnp.int32),
        jnp.zeros((), jnp.int32),
        jnp.asarray(False),
    )

    def cond(s):
        return (~s.done) & (s.it < max_iter)

    def body(s):
        labels = _assign(gm, s.cw, s.cm, s.cP)
        new = merge_labels(gm, labels, num_out, "moment")
        # an empty cluster keeps its old center (eqs 70–72 are undefined for it)
        cw = jnp.where(new.mask, new.weights, s.cw)
        cm = jnp.where(new.mask[:, None], new.means, s.cm)
        cP = jnp.where(new.mask[:, None, None], new.covs, s.cP)
        change = jnp.maximum(
            jnp.max(jnp.abs(cw - s.cw)),
            jnp.maximum(jnp.max(jnp.abs(cm - s.cm)), jnp.max(jnp.abs(cP - s.cP))),
        )
        return _KState(cw, cm, cP, labels, s.it + 1, change <= tol)

    s = jax.lax.while_loop(cond, body, s0)
    merged = merge_labels(gm, s.labels, num_out, "moment")
    out, labels_out, overflow, dropped = _util.finalize(gm, merged, s.labels, capacity)
    # pass-through when there is nothing to reduce
    n_in = jnp.sum(gm.mask.astype(jnp.int32))
    small = n_in <= num_out
    ident, lab_id, _, _ = _util.finalize(gm, gm, _util.identity_labels(gm), max(capacity, gm.capacity))
    if capacity < gm.capacity:
        ident = jax.tree_util.tree_map(lambda a: a[:capacity], ident)
        lab_id = jnp.where(lab_id < capacity, lab_id, -1)
    out = jax.tree_util.tree_map(lambda a, b: jnp.where(small, a, b), ident, out)
    labels_out = jnp.where(small, lab_id, labels_out)
    return out, labels_out, s.it, s.done | small


def kmeans(
    gm: GaussianMixture,
    num_out: int,
    *,
    max_iter: int = 100,
    tol: float = 0.0,
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """GMM k-means reduction to ``num_out`` clusters (seed 002 Algorithm 3).

    Initialisation: the heaviest component, then farthest-point selection under the weighted
    Mahalanobis distance of eq 69. Iteration: assign every component to the center at smallest
    eq-69 distance (the center being the merged cluster ``(w_C, mu_C, Sigma_C)``), merge every
    cluster with the moment-preserving merge (eqs 70–72), and repeat until the centers no longer
    change (``max |new - old| <= tol`` over weights, means and covariances; ``tol = 0`` is the
    paper's exact "old = new" test) or ``max_iter`` iterations (a static bound; ``lax.while_loop``).
    An empty cluster keeps its previous center and yields no output component.

    Not reverse-mode differentiable (a while loop over discrete assignments); it has no dynamic
    thresholds.

    Args:
        gm: input mixture, capacity ``K``.
        num_out: static number of clusters, ``1 <= num_out <= K``.
        max_iter: static bound on the iterations.
        tol: static convergence tolerance on the centers.
        capacity: static output capacity (default ``K``; pass ``capacity=num_out`` for a compact
            result).
        key: unused (deterministic initialisation).

    Returns:
        ``(reduced mixture, info)``; ``info.aux`` has ``iterations`` and ``converged``. A mixture
        with at most ``num_out`` live components is returned unchanged (compacted).
    """
    del key
    _validate.validate_mixture(gm)
    num_out = _validate.validate_count(num_out, "num_out", 1, gm.capacity)
    cap = _validate.validate_capacity(capacity, gm, minimum=num_out)
    max_iter = _validate.validate_count(max_iter, "max_iter", 1, 2**31 - 1)
    _validate.validate_nonneg(tol, "tol")
    if isinstance(tol, jax.core.Tracer):
        raise ValueError("tol: must be a static Python float")
    out, labels, it, conv = _kmeans(gm, num_out, max_iter, float(tol), cap)
    info = make_info(gm, out, labels, aux={"iterations": it, "converged": conv})
    return out, info


@pytree_dataclass
class KMeans(Stateless):
    """Reducer config for :func:`kmeans` (all fields static)."""

    num_out: int = static_field(10)
    max_iter: int = static_field(100)
    tol: float = static_field(0.0)
    capacity: int | None = static_field(None)

    __call__ = calls(kmeans)
