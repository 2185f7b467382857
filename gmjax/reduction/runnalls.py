"""Runnalls' greedy KL-bound reduction (Runnalls 2007; the R-GMR baseline of Xu et al.).

Repeatedly merges the pair with the smallest upper bound on the KL discrimination of the merge, with
the moment-preserving merge (seed 002 eqs 70-72), over the engine in :mod:`gmjax.reduction._greedy`
(conventions shared with ``references/reduction_np.py`` are listed there).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._pytree import pytree_dataclass
from gmjax._types import Array
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction._greedy import (
    BLOCK,
    chunked,
    clean_upper,
    finish,
    greedy_steps,
    init_state,
    upper_argmin,
)
from gmjax.reduction.base import CountThreshold, calls

__all__ = ["runnalls", "runnalls_cost", "Runnalls"]


def runnalls_cost(
    wi: Array,
    mi: Array,
    Pi: Array,
    wj: Array,
    mj: Array,
    Pj: Array,
    ldi: Array | None = None,
    ldj: Array | None = None,
    *,
    normalized: bool = False,
) -> Array:
    """Runnalls' upper bound on the KL discrimination caused by merging ``i`` and ``j``.

    ``B(i, j) = 1/2 [(w_i + w_j) log det P_ij - w_i log det P_i - w_j log det P_j]`` with ``P_ij``
    the moment-merged covariance (Runnalls 2007, IEEE TAES 43(3), Theorem 3 / eq 21). Weights as
    stored; broadcasts over leading axes. ``ldi``/``ldj`` are optional precomputed
    ``log det P_i`` / ``log det P_j``. ``normalized`` (static): ``B(i, j) / (w_i + w_j)
    = 1/2 [log det P_ij - l_i log det P_i - l_j log det P_j]`` with ``l_i = w_i / (w_i + w_j)``
    (``l_i = 1/2`` for a pair of zero weight; seed 001 Step 6 rule 2).
    """
    W, _, Pij = gaussian.moment_merge_pair(wi, mi, Pi, wj, mj, Pj, symmetrize=False)  # only its log det
    ldi = gaussian.spd_logdet(Pi) if ldi is None else ldi
    ldj = gaussian.spd_logdet(Pj) if ldj is None else ldj
    if normalized:
        ok = W > 0
        Ws = jnp.where(ok, W, 1.0)
        li = jnp.where(ok, wi / Ws, 0.5)
        lj = jnp.where(ok, wj / Ws, 0.5)
        return 0.5 * (gaussian.spd_logdet(Pij) - li * ldi - lj * ldj)
    return 0.5 * (W * gaussian.spd_logdet(Pij) - wi * ldi - wj * ldj)


@partial(jax.jit, static_argnames=("num_out", "capacity"))
def _runnalls(gm, num_out, threshold, capacity):
    threshold = jax.lax.stop_gradient(threshold)  # piecewise constant: zero gradient a.e.
    block = BLOCK if gm.dim >= 3 else None  # measured: see chunked
    core = chunked(lambda g, t: _runnalls_core(g, num_out, t, capacity), block)
    return core(gm, threshold)


def _initial_costs(gm: GaussianMixture) -> tuple[Array, Array]:
    """The loop's start: the clean ``(K, K)`` pair-cost matrix (:func:`clean_upper`) and every
    slot's ``log det P`` ``(K,)``."""
    w = jnp.where(gm.mask, gm.weights, 0.0)
    ld = gaussian.spd_logdet(gm.covs)
    C = runnalls_cost(
        w[:, None],
        gm.means[:, None],
        gm.covs[:, None],
        w[None, :],
        gm.means[None],
        gm.covs[None],
        ld[:, None],
        ld[None, :],
    )
    return clean_upper(C, gm.mask), ld


def _runnalls_core(gm, num_out, threshold, capacity):
    C, ld = _initial_costs(gm)

    def row_cost(s, i):  # log-determinants carried: only the merged slot's is new
        return runnalls_cost(s.w[i], s.m[i], s.P[i], s.w, s.m, s.P, s.logdet[i], s.logdet)

    body, n_steps = greedy_steps(gm, num_out, threshold, upper_argmin, row_cost)
    s = jax.lax.fori_loop(0, n_steps, body, init_state(gm, C, ld))
    return finish(gm, s, n_steps, capacity)


runnalls = _util.count_threshold_reducer(
    _runnalls,
    "runnalls",
    """Runnalls' greedy KL-bound reduction (Runnalls 2007; the R-GMR baseline of seed 000).

    Repeatedly merges the pair with the smallest :func:`runnalls_cost` (an upper bound on the KL
    discrimination of the merge) until ``num_out`` components remain or the smallest cost exceeds
    ``threshold``.

    Args:
        gm: input mixture, capacity ``K``.
        num_out: static target count, ``1 <= num_out <= K`` (``1`` with a threshold = threshold only).
        threshold: ``()`` non-negative cost bound (default ``inf``), may be traced.
        capacity: static output capacity ``>= num_out`` (default ``K``).
        key: unused.

    Returns:
        ``(reduced mixture, info)``; ``info.cost`` is the summed bound, ``info.aux["merges"]`` the
        merge sequence.
    """,
)


@pytree_dataclass
class Runnalls(CountThreshold):
    """Reducer config for :func:`runnalls`: ``num_out``, ``threshold`` (dynamic), ``capacity``
    (:class:`~gmjax.reduction.base.CountThreshold`)."""

    __call__ = calls(runnalls)
