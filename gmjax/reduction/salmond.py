"""Salmond's joining algorithm (Salmond 1990), over the greedy engine in :mod:`gmjax.reduction._greedy`."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._pytree import pytree_dataclass
from gmjax._types import Array
from gmjax.mixture import moments
from gmjax.reduction import _greedy, _util
from gmjax.reduction.base import CountThreshold, calls

__all__ = ["salmond", "salmond_cost", "Salmond"]


def salmond_cost(wi: Array, mi: Array, wj: Array, mj: Array, Pinv_total: Array) -> Array:
    """Salmond's joining distance ``D^2 = w_i w_j / (w_i + w_j) (m_i - m_j)^T P^{-1} (m_i - m_j)``.

    ``P`` is the covariance of the whole (normalised) mixture (Salmond 1990, "Mixture reduction
    algorithms for target tracking in clutter", SPIE 1305, the joining algorithm). Moment-preserving
    merges leave ``P`` unchanged, so it is computed once.
    """
    s = wi + wj
    ok = s > 0
    coef = jnp.where(ok, wi * wj / jnp.where(ok, s, 1.0), 0.0)
    diff = mi - mj
    return coef * jnp.einsum("...i,ij,...j->...", diff, Pinv_total, diff)


@partial(jax.jit, static_argnames=("num_out", "capacity"))
def _salmond(gm, num_out, threshold, capacity):
    threshold = jax.lax.stop_gradient(threshold)
    return _greedy.chunked(lambda g, t: _salmond_core(g, num_out, t, capacity), _greedy.BLOCK)(gm, threshold)


def _salmond_core(gm, num_out, threshold, capacity):
    w = jnp.where(gm.mask, gm.weights, 0.0)
    _, Ptot = moments(gm)
    Pinv = gaussian.spd_inv(Ptot)
    C = salmond_cost(w[:, None], gm.means[:, None], w[None, :], gm.means[None], Pinv)

    def row_cost(s, i):
        return salmond_cost(s.w[i], s.m[i], s.w, s.m, Pinv)

    body, n_steps = _greedy.greedy_steps(gm, num_out, threshold, _greedy.upper_argmin, row_cost)
    s = jax.lax.fori_loop(0, n_steps, body, _greedy.init_state(gm, _greedy.clean_upper(C, gm.mask)))
    out, info = _greedy.finish(gm, s, n_steps, capacity)
    return out, info


salmond = _util.count_threshold_reducer(
    _salmond,
    "salmond",
    """Salmond's joining algorithm (Salmond 1990).

    Repeatedly merges the pair with the smallest :func:`salmond_cost` (weighted squared distance of
    the means in the metric of the whole mixture's covariance) until ``num_out`` remain or the
    smallest distance exceeds ``threshold``. Arguments as in :func:`runnalls`.
    """,
)


@pytree_dataclass
class Salmond(CountThreshold):
    """Reducer config for :func:`salmond`: ``num_out``, ``threshold`` (dynamic), ``capacity``
    (:class:`~gmjax.reduction.base.CountThreshold`)."""

    __call__ = calls(salmond)
