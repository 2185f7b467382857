"""Constraint-optimised weight adaptation, COWA (Chen, Chang & Smith 2010), over the exact-ISE terms of
:mod:`gmjax.reduction._ise_greedy` (seed 000 eqs 31, 35)."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._pytree import pytree_dataclass
from gmjax._types import Array
from gmjax.metrics import ise
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction._ise_greedy import ISEGreedyState, initial_state, ise_terms, self_term
from gmjax.reduction.base import CountThreshold, calls
from gmjax.reduction.west import west_distance

__all__ = ["cowa", "optimal_weights", "COWA"]


def optimal_weights(S: Array, b: Array, active: Array, total: Array, n_iter: int) -> tuple[Array, Array]:
    """ISE-optimal weights on ``active`` with ``sum w = total`` and ``w >= 0`` (COWA's QP).

    Minimises ``w^T S w - 2 b^T w``: on the active set ``S w = b + nu 1`` with ``nu`` fixed by the
    equality constraint; components that come out negative are removed and the system re-solved
    (``n_iter`` static rounds, all negative components at once). Returns ``(w, active)``; ``w`` is
    NaN when the system is singular (e.g. two identical components: the optimum is not unique) and
    the caller then keeps the input weights. The singular case is detected on a gradient-free solve
    first and the differentiated solve sees the identity instead, so gradients stay finite.
    """
    K = S.shape[0]
    eye = jnp.eye(K, dtype=S.dtype)

    def raw(A, bb, one):
        x = jnp.linalg.solve(A, jnp.stack([bb, one], axis=1))
        u, v = x[:, 0], x[:, 1]
        return u, v, one @ v

    def solve(act):
        A = jnp.where(act[:, None] & act[None, :], S, eye)
        bb = jnp.where(act, b, 0.0)
        one = act.astype(S.dtype)
        u0, v0, den0 = raw(*jax.lax.stop_gradient((A, bb, one)))
        ok = jnp.all(jnp.isfinite(u0)) & jnp.all(jnp.isfinite(v0)) & (den0 != 0) & jnp.isfinite(den0)
        u, v, den = raw(jnp.where(ok, A, eye), jnp.where(ok, bb, 0.0), jnp.where(ok, one, 1.0))
        nu = (total - one @ u) / jnp.where(ok, den, 1.0)
        return jnp.where(act & ok, u + nu * v, jnp.where(ok, 0.0, jnp.nan))

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
    Jhh = self_term(gm, w0)

    def body(step, s):
        # enhanced-West selection: smallest w / det P, merged with its ISE-nearest neighbour
        score = s.w / jnp.exp(gaussian.spd_logdet(s.P))
        i = jnp.argmin(jnp.where(s.mask, score, jnp.inf)).astype(jnp.int32)
        dist = west_distance(s.m[i], s.P[i], s.m, s.P, "ise")
        dist = jnp.where(s.mask & (jnp.arange(K) != i), dist, jnp.inf)
        j = jnp.argmin(dist).astype(jnp.int32)
        W, mm, PP = gaussian.moment_merge_pair(s.w[i], s.m[i], s.P[i], s.w[j], s.m[j], s.P[j])
        w = s.w.at[i].set(W).at[j].set(0.0)
        m = s.m.at[i].set(mm).at[j].set(0.0)
        P = s.P.at[i].set(PP).at[j].set(eye)
        mask = s.mask.at[j].set(False)
        cand = s._replace(w=w, m=m, P=P, mask=mask)
        S, a = ise_terms(cand, gm, w0)
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
        new = ISEGreedyState(
            w_opt,
            m,
            P,
            act,
            labels,
            jnp.sum(act.astype(jnp.int32)),
            cost,
            s.actions.at[step].set(jnp.stack([i, j]).astype(jnp.int32)),
        )
        return jax.tree_util.tree_map(lambda a_, b_: jnp.where(do, a_, b_), new, s)

    n_steps = K - num_out
    s0 = initial_state(gm, w0, n_steps)
    s = jax.lax.fori_loop(0, n_steps, body, s0)
    work = GaussianMixture(s.w, s.m, s.P, s.mask)
    cost = partial(ise, gm)  # the output's ISE to the input
    return _util.finalize_info(gm, work, s.labels, capacity, cost=cost, aux={"actions": s.actions[:n_steps]})


cowa = _util.count_threshold_reducer(
    _cowa,
    "cowa",
    """Constraint-optimised weight adaptation (Chen, Chang & Smith 2010, SPIE 7697).

    Each step merges the component with the smallest ``w / det P`` into its ISE-nearest neighbour
    (the enhanced West selection of that paper), then re-optimises *all* weights to minimise the
    ISE to the original subject to ``sum w = W_0``, ``w >= 0`` (:func:`optimal_weights`;
    components driven negative are discarded). A step is taken only while the resulting ISE is at
    most ``threshold``; reduction stops at ``num_out`` components. Our reading: the paper's
    "weight adaptation after every merge" with an active-set solution of its constrained QP.

    Arguments as in :func:`williams` (``threshold`` is an ISE bound, may be traced).
    """,
)


@pytree_dataclass
class COWA(CountThreshold):
    """Reducer config for :func:`cowa`: ``num_out``, ``threshold`` (dynamic), ``capacity``
    (:class:`~gmjax.reduction.base.CountThreshold`)."""

    __call__ = calls(cowa)
