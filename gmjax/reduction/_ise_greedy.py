"""Greedy reductions that track the exact ISE to the original mixture: Williams and COWA.

Both keep the ISE ``J_hh - 2 J_hr + J_rr`` (seed 000 eqs 31, 35) of the current reduced mixture ``r``
against the original ``h`` in closed form and update its terms for every candidate action:

* merging ``(i, j)`` into ``c``: ``J_hr' = J_hr - w_i a_i - w_j a_j + w_c a_c`` and
  ``J_rr' = J_rr - 2 w_i (Sw)_i - 2 w_j (Sw)_j + w_i^2 S_ii + w_j^2 S_jj + 2 w_i w_j S_ij
  + w_c^2 S_cc + 2 w_c sum_{k != i, j} w_k S_ck``,
* pruning ``i`` and rescaling the rest by ``s = W / (W - w_i)``:
  ``J_hr' = s (J_hr - w_i a_i)``, ``J_rr' = s^2 (J_rr - 2 w_i (Sw)_i + w_i^2 S_ii)``,

with ``S`` the overlap matrix of ``r`` and ``a_k = sum_o w_o N(m_o; m_k, P_o + P_k)``.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from gmjax._pytree import pytree_dataclass, static_field
from gmjax.reduction._util import ise
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction._base import ReductionInfo, Stateless, make_info
from gmjax.reduction._greedy import _merge_broadcast, west_distance

__all__ = ["williams", "cowa", "Williams", "COWA", "optimal_weights"]


def _overlap(ma, Pa, mb, Pb):
    return jnp.exp(_util.log_gauss(ma, mb, Pa + Pb))


class _WState(NamedTuple):
    w: jax.Array
    m: jax.Array
    P: jax.Array
    mask: jax.Array
    labels: jax.Array
    n_live: jax.Array
    cost: jax.Array
    actions: jax.Array


def _initial_state(gm: GaussianMixture, w0: jax.Array, n_steps: int) -> "_WState":
    """The greedy loop's state before any action (shared by Williams and COWA)."""
    return _WState(
        w0, gm.means, gm.covs, gm.mask, _util.identity_labels(gm),
        jnp.sum(gm.mask.astype(jnp.int32)), jnp.zeros((), w0.dtype),
        jnp.full((max(n_steps, 1), 2), -2, jnp.int32),
    )


def _terms(s, gm0, w0):
    S = _overlap(s.m[:, None], s.P[:, None], s.m[None], s.P[None])
    live2 = s.mask[:, None] & s.mask[None, :]
    S = jnp.where(live2, S, 0.0)
    A = _overlap(s.m[:, None], s.P[:, None], gm0.means[None], gm0.covs[None])
    a = jnp.where(s.mask, A @ w0, 0.0)
    return S, a


@partial(jax.jit, static_argnames=("num_out", "allow_prune", "capacity"))
def _williams(gm, num_out, threshold, allow_prune, capacity):
    K = gm.capacity
    d = gm.dim
    eye = jnp.eye(d, dtype=gm.covs.dtype)
    w0 = jnp.where(gm.mask, gm.weights, 0.0)
    Jhh = w0 @ jnp.where(
        gm.mask[:, None] & gm.mask[None, :],
        _overlap(gm.means[:, None], gm.covs[:, None], gm.means[None], gm.covs[None]),
        0.0,
    ) @ w0
    upper = jnp.arange(K)[:, None] < jnp.arange(K)[None, :]

    def body(step, s):
        S, a = _terms(s, gm, w0)
        w = s.w
        Sw = S @ w
        Jrr = w @ Sw
        Jhr = w @ a
        # merge candidates (K, K)
        Wc, mc, Pc = _merge_broadcast(w[:, None], s.m[:, None], s.P[:, None], w[None], s.m[None], s.P[None])
        Sc = _overlap(mc[:, :, None], Pc[:, :, None], s.m[None, None], s.P[None, None])  # (K,K,K)
        Sc = jnp.where(s.mask[None, None, :], Sc, 0.0)
        ac = _overlap(mc[:, :, None], Pc[:, :, None], gm.means[None, None], gm.covs[None, None]) @ w0
        Scc = jnp.exp(_util.log_gauss(mc, mc, 2.0 * Pc))
        Sc_w = Sc @ w
        ii = jnp.arange(K)
        Sc_i = Sc[ii[:, None], ii[None, :], ii[:, None]]  # S(c_ij, i)
        Sc_j = Sc[ii[:, None], ii[None, :], ii[None, :]]  # S(c_ij, j)
        rest = Sc_w - w[:, None] * Sc_i - w[None, :] * Sc_j
        wi, wj = w[:, None], w[None, :]
        Sii = jnp.diag(S)
        Jhr_m = Jhr - wi * a[:, None] - wj * a[None, :] + Wc * ac
        Jrr_m = (
            Jrr - 2 * wi * Sw[:, None] - 2 * wj * Sw[None, :]
            + wi**2 * Sii[:, None] + wj**2 * Sii[None, :] + 2 * wi * wj * S
            + Wc**2 * Scc + 2 * Wc * rest
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
        return _WState(
            w_new, m_new, P_new, mask, labels, s.n_live - do.astype(jnp.int32),
            jnp.where(do, c, s.cost), s.actions.at[step].set(act),
        )

    n_steps = K - num_out
    s0 = _initial_state(gm, w0, n_steps)
    s = jax.lax.fori_loop(0, n_steps, body, s0)
    work = GaussianMixture(s.w, s.m, s.P, s.mask)
    out, labels, overflow, dropped = _util.finalize(gm, work, s.labels, capacity)
    pruned = jnp.sum(w0) - jnp.sum(jnp.where(s.labels >= 0, w0, 0.0))
    return out, make_info(
        gm, out, labels, overflow=overflow, pruned_mass=pruned + dropped, cost=ise(gm, out),
        aux={"actions": s.actions[:n_steps]},
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
    _util.validate_mixture(gm)
    num_out = _util.validate_count(num_out, "num_out", 1, gm.capacity)
    cap = _util.validate_capacity(capacity, gm, minimum=num_out)
    _util.validate_nonneg(threshold, "threshold")
    thr = jnp.asarray(jnp.inf if threshold is None else threshold, gm.weights.dtype)
    return _williams(gm, num_out, thr, bool(allow_prune), cap)


# ----------------------------------------------------------------------------- COWA


def optimal_weights(S, b, active, total, n_iter):
    """ISE-optimal weights on ``active`` with ``sum w = total`` and ``w >= 0`` (COWA's QP).

    Minimises ``w^T S w - 2 b^T w``: on the active set ``S w = b + nu 1`` with ``nu`` fixed by the
    equality constraint; components that come out negative are removed and the system re-solved
    (``n_iter`` static rounds, all negative components at once). Returns ``(w, active)``; if the
    solve is not finite the input weights are kept by the caller.
    """
    K = S.shape[0]
    eye = jnp.eye(K, dtype=S.dtype)

    def solve(act):
        A = jnp.where(act[:, None] & act[None, :], S, eye)
        bb = jnp.where(act, b, 0.0)
        one = act.astype(S.dtype)
        x = jnp.linalg.solve(A, jnp.stack([bb, one], axis=1))
        u, v = x[:, 0], x[:, 1]
        nu = (total - one @ u) / (one @ v)
        return jnp.where(act, u + nu * v, 0.0)

    def body(_, carry):
        w, act = carry
        neg = act & (w < 0)
        act = act & ~neg
        w = jnp.where(jnp.any(neg), solve(act), w)
        return w, act

    w = solve(active)
    return jax.lax.fori_loop(0, n_iter, body, (w, active))


@partial(jax.jit, static_argnames=("num_out", "capacity"))
def _cowa(gm, num_out, threshold, capacity):
    K = gm.capacity
    d = gm.dim
    eye = jnp.eye(d, dtype=gm.covs.dtype)
    w0 = jnp.where(gm.mask, gm.weights, 0.0)
    total0 = jnp.sum(w0)
    Jhh = w0 @ jnp.where(
        gm.mask[:, None] & gm.mask[None, :],
        _overlap(gm.means[:, None], gm.covs[:, None], gm.means[None], gm.covs[None]),
        0.0,
    ) @ w0

    def body(step, s):
        # enhanced-West selection: smallest w / det P, merged with its ISE-nearest neighbour
        score = s.w / jnp.exp(_util.logdet(s.P))
        i = jnp.argmin(jnp.where(s.mask, score, jnp.inf)).astype(jnp.int32)
        dist = west_distance(s.m[i], s.P[i], s.m, s.P, "ise")
        dist = jnp.where(s.mask & (jnp.arange(K) != i), dist, jnp.inf)
        j = jnp.argmin(dist).astype(jnp.int32)
        W, mm, PP = _util.merge_pair(s.w[i], s.m[i], s.P[i], s.w[j], s.m[j], s.P[j])
        w = s.w.at[i].set(W).at[j].set(0.0)
        m = s.m.at[i].set(mm).at[j].set(0.0)
        P = s.P.at[i].set(PP).at[j].set(eye)
        mask = s.mask.at[j].set(False)
        cand = s._replace(w=w, m=m, P=P, mask=mask)
        S, a = _terms(cand, gm, w0)
        w_opt, act = optimal_weights(S, a, mask, total0, K)
        ok = jnp.all(jnp.isfinite(w_opt)) & jnp.any(act)
        w_opt = jnp.where(ok, w_opt, w)
        act = jnp.where(ok, act, mask)
        cost = jnp.maximum(Jhh - 2 * w_opt @ a + w_opt @ S @ w_opt, 0.0)
        do = (s.n_live > num_out) & jnp.isfinite(dist[j]) & (cost <= threshold)
        labels = jnp.where(s.labels == j, i, s.labels)
        labels = jnp.where(act[jnp.maximum(labels, 0)] & (labels >= 0), labels, -1)
        P = jnp.where(act[:, None, None], P, eye)
        m = jnp.where(act[:, None], m, 0.0)
        new = _WState(
            w_opt, m, P, act, labels, jnp.sum(act.astype(jnp.int32)), cost,
            s.actions.at[step].set(jnp.stack([i, j]).astype(jnp.int32)),
        )
        return jax.tree_util.tree_map(lambda a_, b_: jnp.where(do, a_, b_), new, s)

    n_steps = K - num_out
    s0 = _initial_state(gm, w0, n_steps)
    s = jax.lax.fori_loop(0, n_steps, body, s0)
    work = GaussianMixture(s.w, s.m, s.P, s.mask)
    out, labels, overflow, dropped = _util.finalize(gm, work, s.labels, capacity)
    return out, make_info(
        gm, out, labels, overflow=overflow, pruned_mass=dropped, cost=ise(gm, out),
        aux={"actions": s.actions[:n_steps]},
    )


def cowa(
    gm: GaussianMixture,
    num_out: int,
    threshold: Any = None,
    *,
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """Constraint-optimised weight adaptation (Chen, Chang & Smith 2010, SPIE 7697).

    Each step merges the component with the smallest ``w / det P`` into its ISE-nearest neighbour
    (the enhanced West selection of that paper), then re-optimises *all* weights to minimise the
    ISE to the original subject to ``sum w = W_0``, ``w >= 0`` (:func:`optimal_weights`;
    components driven negative are discarded). A step is taken only while the resulting ISE is at
    most ``threshold``; reduction stops at ``num_out`` components. Our reading: the paper's
    "weight adaptation after every merge" with an active-set solution of its constrained QP.

    Arguments as in :func:`williams` (``threshold`` is an ISE bound, may be traced).
    """
    del key
    _util.validate_mixture(gm)
    num_out = _util.validate_count(num_out, "num_out", 1, gm.capacity)
    cap = _util.validate_capacity(capacity, gm, minimum=num_out)
    _util.validate_nonneg(threshold, "threshold")
    thr = jnp.asarray(jnp.inf if threshold is None else threshold, gm.weights.dtype)
    return _cowa(gm, num_out, thr, cap)


@pytree_dataclass
class Williams(Stateless):
    """Reducer config for :func:`williams` (``threshold`` dynamic)."""

    num_out: int = static_field(10)
    threshold: Any = float("inf")
    allow_prune: bool = static_field(True)
    capacity: int | None = static_field(None)

    def __call__(self, gm, *, key=None):
        return williams(
            gm, self.num_out, self.threshold, allow_prune=self.allow_prune,
            capacity=self.capacity, key=key,
        )


@pytree_dataclass
class COWA(Stateless):
    """Reducer config for :func:`cowa` (``threshold`` dynamic)."""

    num_out: int = static_field(10)
    threshold: Any = float("inf")
    capacity: int | None = static_field(None)

    def __call__(self, gm, *, key=None):
        return cowa(gm, self.num_out, self.threshold, capacity=self.capacity, key=key)
