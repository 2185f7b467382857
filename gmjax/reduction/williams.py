"""Williams & Maybeck (2003) greedy ISE reduction over the exact-ISE terms of
:mod:`gmjax.reduction._ise_greedy` (seed 000 eqs 31, 35)."""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._pytree import pytree_dataclass, static_field
from gmjax.metrics import ise
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction._ise_greedy import ISEGreedyState, initial_state, ise_terms, overlap, self_term
from gmjax.reduction.base import ReductionInfo, Stateless, calls

__all__ = ["williams", "Williams"]


@partial(jax.jit, static_argnames=("num_out", "allow_prune", "capacity"))
def _williams(gm, num_out, threshold, allow_prune, capacity):
    """The greedy loop of :func:`williams`. One function because the step body closes over the
    original mixture's ISE terms (``J_hh``, the overlaps) that every candidate action updates."""
    K = gm.capacity
    d = gm.dim
    eye = jnp.eye(d, dtype=gm.covs.dtype)
    w0 = jnp.where(gm.mask, gm.weights, 0.0)
    Jhh = self_term(gm, w0)
    upper = jnp.arange(K)[:, None] < jnp.arange(K)[None, :]

    def body(step, s):
        S, a = ise_terms(s, gm, w0)
        w = s.w
        Sw = S @ w
        Jrr = w @ Sw
        Jhr = w @ a
        # merge candidates (K, K)
        Wc, mc, Pc = gaussian.moment_merge_pair(
            w[:, None], s.m[:, None], s.P[:, None], w[None], s.m[None], s.P[None]
        )
        Sc = overlap(mc[:, :, None], Pc[:, :, None], s.m[None, None], s.P[None, None])  # (K,K,K)
        Sc = jnp.where(s.mask[None, None, :], Sc, 0.0)
        ac = overlap(mc[:, :, None], Pc[:, :, None], gm.means[None, None], gm.covs[None, None]) @ w0
        Scc = jnp.exp(gaussian.spd_logpdf(mc, mc, 2.0 * Pc))
        Sc_w = Sc @ w
        ii = jnp.arange(K)
        Sc_i = Sc[ii[:, None], ii[None, :], ii[:, None]]  # S(c_ij, i)
        Sc_j = Sc[ii[:, None], ii[None, :], ii[None, :]]  # S(c_ij, j)
        rest = Sc_w - w[:, None] * Sc_i - w[None, :] * Sc_j
        wi, wj = w[:, None], w[None, :]
        Sii = jnp.diag(S)
        Jhr_m = Jhr - wi * a[:, None] - wj * a[None, :] + Wc * ac
        Jrr_m = (
            Jrr
            - 2 * wi * Sw[:, None]
            - 2 * wj * Sw[None, :]
            + wi**2 * Sii[:, None]
            + wj**2 * Sii[None, :]
            + 2 * wi * wj * S
            + Wc**2 * Scc
            + 2 * Wc * rest
        )
        cost_m = Jhh - 2 * Jhr_m + Jrr_m
        valid_m = upper & s.mask[:, None] & s.mask[None, :]
        cost_m = jnp.where(valid_m, cost_m, jnp.inf).reshape(-1)
        # prune candidates (K,)
        Wt = jnp.sum(w)
        rem = Wt - w
        okp = s.mask & (rem > 0) & (s.n_live > 1)
        sc = jnp.where(okp, Wt / jnp.where(okp, rem, 1.0), 0.0)
        Jhr_p = sc * (Jhr - w * a)
        Jrr_p = sc**2 * (Jrr - 2 * w * Sw + w**2 * Sii)
        cost_p = jnp.where(okp, Jhh - 2 * Jhr_p + Jrr_p, jnp.inf)
        if not allow_prune:
            cost_p = jnp.full_like(cost_p, jnp.inf)
        allc = jnp.concatenate([cost_m, cost_p])
        k = jnp.argmin(allc)
        c = jnp.maximum(allc[k], 0.0)
        do = (s.n_live > num_out) & (c <= threshold) & jnp.isfinite(allc[k])
        is_merge = k < K * K
        i = jnp.where(is_merge, k // K, k - K * K).astype(jnp.int32)
        j = jnp.where(is_merge, k % K, k - K * K).astype(jnp.int32)
        dm = do & is_merge
        dp = do & ~is_merge
        # merge: slot i <- c, slot j emptied
        w_new = jnp.where(dm, w.at[i].set(Wc[i, j]).at[j].set(0.0), w)
        m_new = jnp.where(dm, s.m.at[i].set(mc[i, j]).at[j].set(0.0), s.m)
        P_new = jnp.where(dm, s.P.at[i].set(Pc[i, j]).at[j].set(eye), s.P)
        # prune: slot i emptied, the rest rescaled
        w_new = jnp.where(dp, (w * sc[i]).at[i].set(0.0), w_new)
        m_new = jnp.where(dp, m_new.at[i].set(0.0), m_new)
        P_new = jnp.where(dp, P_new.at[i].set(eye), P_new)
        mask = jnp.where(do, s.mask.at[j].set(False), s.mask)
        labels = jnp.where(dm & (s.labels == j), i, s.labels)
        labels = jnp.where(dp & (s.labels == i), -1, labels)
        act = jnp.where(do, jnp.stack([i, jnp.where(dm, j, -1)]), -2).astype(jnp.int32)
        return ISEGreedyState(
            w_new,
            m_new,
            P_new,
            mask,
            labels,
            s.n_live - do.astype(jnp.int32),
            jnp.where(do, c, s.cost),
            s.actions.at[step].set(act),
        )

    n_steps = K - num_out
    s0 = initial_state(gm, w0, n_steps)
    s = jax.lax.fori_loop(0, n_steps, body, s0)
    work = GaussianMixture(s.w, s.m, s.P, s.mask)
    pruned = jnp.sum(w0) - jnp.sum(jnp.where(s.labels >= 0, w0, 0.0))
    return _util.finalize_info(
        gm,
        work,
        s.labels,
        capacity,
        cost=partial(ise, gm),  # the output's ISE to the input
        aux={"actions": s.actions[:n_steps]},
        pruned_mass=pruned,
    )


def williams(
    gm: GaussianMixture,
    num_out: int,
    threshold: Any = None,
    *,
    allow_prune: bool = True,
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """Williams & Maybeck (2003) greedy ISE reduction ("Cost-function-based Gaussian mixture
    reduction for target tracking", FUSION).

    At every step every pairwise moment-preserving merge and (with ``allow_prune``) every deletion
    of one component with renormalisation is scored by the exact ISE of the resulting mixture to
    the *original*; the best action is taken. Stops at ``num_out`` components or when the best ISE
    exceeds ``threshold``. Each step costs ``O(K^2 (K + K_0))`` Gaussian overlaps.

    Args:
        gm: input mixture, capacity ``K``.
        num_out: static target count.
        threshold: ISE bound (default ``inf``), may be traced.
        allow_prune: static; include deletions.
        capacity: static output capacity (default ``K``).
        key: unused.

    Returns:
        ``(reduced, info)``; ``info.cost`` the final ISE, ``info.aux["actions"]`` rows
        ``(i, j)`` for a merge, ``(i, -1)`` for a deletion, ``(-2, -2)`` for no action.
    """
    del key
    return _util.reduce_count_threshold(
        _williams, gm, num_out, threshold, capacity, allow_prune=bool(allow_prune)
    )


@pytree_dataclass
class Williams(Stateless):
    """Reducer config for :func:`williams` (``threshold`` dynamic)."""

    num_out: int = static_field(10)
    threshold: Any = float("inf")
    allow_prune: bool = static_field(True)
    capacity: int | None = static_field(None)

    __call__ = calls(williams)
