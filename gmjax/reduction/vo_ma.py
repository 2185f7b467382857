"""Threshold pruning and Mahalanobis merging of the GM-PHD filter (Vo & Ma 2006, Table II), hard or
relaxed (differentiable in its thresholds).

**The relaxation** (``VoMa(mode="soft" | "straight_through")``, :func:`relaxed_vo_ma`). The hard
reduction decides ``w > T`` to survive pruning and ``d <= U`` to join a merge, so a loss is piecewise
constant in ``T`` and ``U``; the relaxation replaces each decision by a soft gate
(:func:`gmjax.reduction.relax.soft_step`, the relaxation the other reducers use):

* pruning: component ``i`` keeps the weight ``a_i = g_i w_i`` with ``g_i = sigma((w_i - T) / tau_T)``;
* merging: Vo–Ma's loop over ``K`` steps; step ``s`` picks the heaviest component whose unmerged
  fraction ``r_i`` is above 1/2 (a hard, piecewise-constant choice, as the paper's argmax) and gives
  every component the membership ``L_i = r_i sigma((U - d_i) / tau_U)`` (the pick itself: ``r_j``),
  ``d_i = (m_i - m_j)^T P_i^{-1} (m_i - m_j)`` (Table II, the candidate's covariance); cluster ``s`` is
  the moment-preserving merge of the ``L_i a_i``-weighted components and ``r_i -= L_i``;
* the ``max_components`` heaviest clusters are kept (Table II's ``J_max``).

The relaxed weights are **not** renormalised (the PHD convention of the paper: pruned weight is lost;
the hard :func:`vo_ma` rescales to the input's total); ``info.pruned_mass`` is what was removed
(soft-pruned weight, fractions left unmerged, clusters beyond ``J_max``). With ``tau_T = tau_U = 0``
every gate is 0/1 and the result equals :func:`vo_ma` scaled back by ``(total - pruned) / total``
(tested), i.e. Table II. ``mode="straight_through"`` gives the hard forward pass with the
relaxation's gradient.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp

from gmjax import _validate, gaussian
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array
from gmjax.mixture import GaussianMixture, heaviest_slots, sanitize
from gmjax.reduction import _util
from gmjax.reduction.base import ReductionInfo, Stateless, make_info
from gmjax.reduction.merge import merge_labels
from gmjax.reduction.prune import _keep
from gmjax.reduction.relax import negligible_floor, soft_step, validate_mode

__all__ = ["vo_ma", "relaxed_vo_ma", "VoMa", "RelaxedVoMa"]


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
    return _util.finalize_info(
        gm, out, kept_labels, capacity, pruned_mass=pruned + info.pruned_mass, overflow=info.overflow
    )


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
    (prune_threshold, merge_threshold), bad = _util.replace_nans(
        (prune_threshold, 1e-5), (merge_threshold, 4.0)
    )
    _validate.validate_mixture(gm)
    _validate.validate_nonneg(prune_threshold, "prune_threshold")
    _validate.validate_nonneg(merge_threshold, "merge_threshold")
    if max_components is not None:
        max_components = _validate.validate_count(max_components, "max_components", 1, gm.capacity)
    cap = _validate.validate_capacity(capacity, gm)
    dt = gm.weights.dtype
    out = _vo_ma(gm, jnp.asarray(prune_threshold, dt), jnp.asarray(merge_threshold, dt), max_components, cap)
    return _util.unchanged_if_nan(bad, gm, out)


def _safe_div(a, b):
    ok = b > 0
    return jnp.where(ok, a / jnp.where(ok, b, 1.0), 0.0)


def relaxed_vo_ma(
    gm: GaussianMixture,
    prune_threshold: Any = 1e-5,
    merge_threshold: Any = 4.0,
    prune_temperature: Any = 0.0,
    merge_temperature: Any = 0.0,
    *,
    max_components: int | None = None,
    mode: str = "soft",
) -> tuple[GaussianMixture, ReductionInfo]:
    """Relaxed Vo–Ma reduction (module docstring).

    Args:
        gm: the intensity, capacity ``K`` (weights need not sum to 1).
        prune_threshold, merge_threshold: ``T``, ``U`` (traced).
        prune_temperature, merge_temperature: ``tau_T`` (weight units), ``tau_U`` (squared Mahalanobis
            units), ``>= 0`` (traced); 0 is the hard rule.
        max_components: static ``J_max`` (default ``K``); the output has ``J_max`` slots, heaviest first.
        mode: ``"soft"`` or ``"straight_through"`` (or ``"hard"``: the gates are 0/1 whatever the
            temperatures).

    Returns:
        ``(reduced, info)``.
    """
    validate_mode(mode)
    K = gm.capacity
    J = K if max_components is None else int(max_components)
    if not 1 <= J <= K:
        raise ValueError(f"max_components: must lie in [1, {K}], got {max_components}")
    dtype = gm.weights.dtype
    w = jnp.where(gm.mask, gm.weights, 0.0)
    total = jnp.sum(w)
    T = jnp.asarray(prune_threshold, dtype)
    U = jnp.asarray(merge_threshold, dtype)
    g = jnp.where(gm.mask, soft_step(w - T, prune_temperature, mode=mode, strict=True), 0.0)
    a = g * w
    # a relaxed gate keeps every component live; one whose kept weight is below rounding (eps^2 of the
    # total) would only square its weight in the merge's derivative and underflow to a NaN gradient
    floor = (
        jnp.maximum(
            negligible_floor(prune_temperature, mode, dtype), negligible_floor(merge_temperature, mode, dtype)
        )
        * total
    )
    alive = gm.mask & (g > 0) & ~(a < floor)
    heaviest = jnp.argmax(jnp.where(gm.mask, w, -jnp.inf))
    rescue = ~jnp.any(alive) & jnp.any(gm.mask)  # as VoMa: a mixture is never emptied
    alive = jnp.where(rescue, jnp.arange(K) == heaviest, alive)
    a = jnp.where(rescue & (jnp.arange(K) == heaviest), w, a)
    idx = jnp.arange(K)

    def gates(j):
        """``(K,)`` soft memberships in the cluster centred on ``j`` (1 for ``j`` itself)."""
        dist = gaussian.spd_inv_quad(gm.means - gm.means[j], gm.covs)
        s = soft_step(U - dist, merge_temperature, mode=mode)
        return jnp.where(idx == j, 1.0, s)

    # the picks are discrete choices: find them on stopped values (no gradient through the loop) ...
    w_stop = jax.lax.stop_gradient(w)

    def pick(r, _):
        avail = r > 0.5
        j = jnp.argmax(jnp.where(avail, w_stop, -jnp.inf))
        L = jnp.where(jnp.any(avail) & alive, r * jax.lax.stop_gradient(gates(j)), 0.0)
        return r - L, (j, jnp.any(avail))

    r0 = alive.astype(dtype)
    _, (picks, active) = jax.lax.scan(pick, r0, None, length=K)
    # ... then the memberships as a differentiable function of the thresholds, without a loop:
    # L_s = r_s * S_s with r_s = r_0 * prod_{t < s} (1 - S_t)
    S = jnp.where(active[:, None], jax.vmap(gates)(picks), 0.0)  # (K steps, K components)
    keep_frac = jax.lax.associative_scan(jnp.multiply, 1.0 - S, axis=0)
    r = r0[None, :] * jnp.concatenate([jnp.ones((1, K), dtype), keep_frac[:-1]], axis=0)
    member = jnp.where(alive[None, :], r * S, 0.0)
    cw = member * a[None, :]  # (K clusters, K components)
    W = jnp.sum(cw, axis=1)
    lam = _safe_div(cw, W[:, None])
    mu = lam @ gm.means
    dev = gm.means[None, :, :] - mu[:, None, :]
    cov = jnp.einsum("ck,kij->cij", lam, gm.covs) + jnp.einsum("ck,cki,ckj->cij", lam, dev, dev)
    live = W > 0
    eye = jnp.eye(gm.dim, dtype=dtype)
    cov = jnp.where(live[:, None, None], gaussian.symmetrize(cov), eye)
    keep, _ = heaviest_slots(jax.lax.stop_gradient(W), live, J)
    out = sanitize(GaussianMixture(W[keep], mu[keep], cov[keep], live[keep]))
    n_live = jnp.sum(live.astype(jnp.int32))
    pruned = total - jnp.sum(out.weights)
    labels = jnp.where(alive, jnp.argmax(member, axis=0), -1)  # cluster of the largest share
    pos = jnp.full(K, -1, jnp.int32).at[keep].set(jnp.where(live[keep], jnp.arange(J, dtype=jnp.int32), -1))
    labels = jnp.where(labels >= 0, pos[jnp.maximum(labels, 0)], -1)
    info = make_info(gm, out, labels, pruned_mass=pruned, overflow=n_live > J, aux={"n_clusters": n_live})
    return out, info


@pytree_dataclass
class VoMa(Stateless):
    """Reducer config for :func:`vo_ma` (thresholds dynamic); ``mode`` (static) ``"soft"`` or
    ``"straight_through"`` is the relaxation :func:`relaxed_vo_ma` with the temperatures
    ``prune_temperature`` (weight units) and ``merge_temperature`` (squared Mahalanobis units), whose
    output keeps the PHD convention (not rescaled, see the module docstring)."""

    prune_threshold: Any = 1e-5
    merge_threshold: Any = 4.0
    max_components: int | None = static_field(None)
    capacity: int | None = static_field(None)
    prune_temperature: Any = 0.0
    merge_temperature: Any = 0.0
    mode: str = static_field("hard")

    def __call__(
        self, gm: GaussianMixture, *, key: Array | None = None
    ) -> tuple[GaussianMixture, ReductionInfo]:
        if self.mode == "hard":
            return vo_ma(
                gm,
                self.prune_threshold,
                self.merge_threshold,
                self.max_components,
                capacity=self.capacity,
                key=key,
            )
        out, info = relaxed_vo_ma(
            gm,
            self.prune_threshold,
            self.merge_threshold,
            self.prune_temperature,
            self.merge_temperature,
            max_components=self.max_components,
            mode=self.mode,
        )
        if self.capacity is None:
            return out, info
        cap = _validate.validate_capacity(self.capacity, gm)
        fitted, labels, overflow, dropped = _util.finalize(gm, out, info.labels, cap)
        return fitted, info._replace(
            labels=labels, overflow=info.overflow | overflow, pruned_mass=info.pruned_mass + dropped
        )


def RelaxedVoMa(
    prune_threshold: Any = 1e-5,
    merge_threshold: Any = 4.0,
    prune_temperature: Any = 0.0,
    merge_temperature: Any = 0.0,
    *,
    max_components: int | None = None,
    mode: str = "soft",
) -> VoMa:
    """The relaxed Vo–Ma reducer: ``VoMa(mode=mode, ...)`` with the temperatures (the 0.2 name and
    argument order). ``RelaxedVoMa(T, U)`` with zero temperatures is Table II on an unnormalised
    intensity; ``mode="hard"`` gives :func:`vo_ma` itself."""
    validate_mode(mode)
    return VoMa(
        prune_threshold=prune_threshold,
        merge_threshold=merge_threshold,
        max_components=max_components,
        prune_temperature=prune_temperature,
        merge_temperature=merge_temperature,
        mode=mode,
    )
