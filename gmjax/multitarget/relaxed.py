"""A relaxed Vo–Ma pruning and merging for PHD intensities: differentiable in its thresholds.

:class:`gmjax.reduction.VoMa` makes hard decisions (``w > T`` to survive pruning, ``d <= U`` to join a
merge), so a loss is piecewise constant in ``T`` and ``U``. :class:`RelaxedVoMa` replaces each by a
soft gate (:func:`gmjax.reduction.relax.soft_step`, the relaxation the other reducers use):

* pruning: component ``i`` keeps the weight ``a_i = g_i w_i`` with ``g_i = sigma((w_i - T) / tau_T)``;
* merging: Vo–Ma's loop over ``K`` steps; step ``s`` picks the heaviest component whose unmerged
  fraction ``r_i`` is above 1/2 (a hard, piecewise-constant choice, as the paper's argmax) and gives
  every component the membership ``L_i = r_i sigma((U - d_i) / tau_U)`` (the pick itself: ``r_j``),
  ``d_i = (m_i - m_j)^T P_i^{-1} (m_i - m_j)`` (Table II, the candidate's covariance); cluster ``s`` is
  the moment-preserving merge of the ``L_i a_i``-weighted components and ``r_i -= L_i``;
* the ``max_components`` heaviest clusters are kept (Table II's ``J_max``).

The weights are **not** renormalised (the PHD convention of the paper: pruned weight is lost);
``info.pruned_mass`` is what was removed (soft-pruned weight, fractions left unmerged, clusters beyond
``J_max``). With ``tau_T = tau_U = 0`` every gate is 0/1 and the result equals
:func:`gmjax.reduction.vo_ma` scaled back by ``(total - pruned) / total`` (tested), i.e. Table II.
``mode="straight_through"`` gives the hard forward pass with the relaxation's gradient.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._pytree import pytree_dataclass, static_field
from gmjax.mixture import GaussianMixture, sanitize
from gmjax.reduction.base import EmptyState, ReductionInfo, make_info
from gmjax.reduction.relax import negligible_floor, soft_step, validate_mode

__all__ = ["RelaxedVoMa", "relaxed_vo_ma"]


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
    _, keep = jax.lax.top_k(jnp.where(live, jax.lax.stop_gradient(W), -jnp.inf), J)
    out = sanitize(GaussianMixture(W[keep], mu[keep], cov[keep], live[keep]))
    n_live = jnp.sum(live.astype(jnp.int32))
    pruned = total - jnp.sum(out.weights)
    labels = jnp.where(alive, jnp.argmax(member, axis=0), -1)  # cluster of the largest share
    pos = jnp.full(K, -1, jnp.int32).at[keep].set(jnp.where(live[keep], jnp.arange(J, dtype=jnp.int32), -1))
    labels = jnp.where(labels >= 0, pos[jnp.maximum(labels, 0)], -1)
    info = make_info(gm, out, labels, pruned_mass=pruned, overflow=n_live > J, aux={"n_clusters": n_live})
    return out, info


@pytree_dataclass
class RelaxedVoMa:
    """Reducer config for :func:`relaxed_vo_ma` (thresholds and temperatures dynamic; a Reducer).

    ``RelaxedVoMa(T, U)`` with zero temperatures is Vo & Ma's Table II on an unnormalised intensity.
    """

    prune_threshold: Any = 1e-5
    merge_threshold: Any = 4.0
    prune_temperature: Any = 0.0
    merge_temperature: Any = 0.0
    max_components: int | None = static_field(None)
    mode: str = static_field("soft")

    def init(self, capacity: int) -> EmptyState:
        """The (empty) state."""
        del capacity
        return EmptyState()

    def reduce(
        self, gm: GaussianMixture, state: Any, *, key: jax.Array | None = None
    ) -> tuple[GaussianMixture, Any, ReductionInfo]:
        """``(reduced, state, info)``."""
        out, info = self(gm, key=key)
        return out, state, info

    def __call__(
        self, gm: GaussianMixture, *, key: jax.Array | None = None
    ) -> tuple[GaussianMixture, ReductionInfo]:
        del key
        return relaxed_vo_ma(
            gm,
            self.prune_threshold,
            self.merge_threshold,
            self.prune_temperature,
            self.merge_temperature,
            max_components=self.max_components,
            mode=self.mode,
        )
