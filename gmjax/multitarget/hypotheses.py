"""The joint association hypotheses of a labelled multi-Bernoulli update, drawn and weighed.

A joint hypothesis gives each of ``N`` tracks a choice ``gamma_i`` among ``A = M + 2``: ``0`` (the
track does not exist), ``1`` (exists, missed) or ``1 + j`` (exists, detected by ``z_j``), no
measurement taken twice; its weight is ``prod_i eta_i(gamma_i)`` for a cost matrix ``log eta (N, A)``
(:func:`gmjax.multitarget.lmb.joint_costs`). This module draws hypotheses with the Gibbs sampler of
B.-N. Vo, B.-T. Vo & H. G. Hoang, "An efficient implementation of the generalized labeled
multi-Bernoulli filter", IEEE TSP 65(8), 2017 (Algorithm 1, the joint existence/association variable),
keeps the distinct ones and weighs them exactly: fixed shapes throughout (``G`` rows), so it runs under
``jit`` and ``vmap``.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from gmjax._types import Array, PRNGKey

__all__ = [
    "gibbs_sample",
    "distinct_rows",
    "hypothesis_marginals",
    "gibbs_uniforms",
    "log_mixture_likelihood",
]


def _log(x: Array) -> Array:
    pos = x > 0
    return jnp.where(pos, jnp.log(jnp.where(pos, x, 1.0)), -jnp.inf)


def log_mixture_likelihood(weights: Array, log_q: Array) -> Array:
    """``(N, M)`` ``log sum_c w_ic q_icj`` in the log domain (``-inf`` where no term is positive), so a
    far measurement neither underflows nor gives unbounded derivatives."""
    terms = _log(weights)[:, :, None] + log_q
    top = jnp.max(terms, axis=1)
    ok = top > -jnp.inf
    top_safe = jnp.where(ok, top, 0.0)
    total = jnp.sum(jnp.exp(terms - top_safe[:, None, :]), axis=1)
    return jnp.where(ok, top_safe + jnp.log(jnp.where(ok, total, 1.0)), -jnp.inf)


def gibbs_sample(log_eta: Array, live: Array, uniforms: Array) -> Array:
    """The Gibbs sampler of Vo, Vo & Hoang 2017 (Algorithm 1, joint variable): ``(G, N)`` int32 rows.

    Row 0 is every live track missed (``gamma = 1``; ``0`` for empty slots). Row ``g`` starts from row
    ``g - 1`` and draws, for ``i = 0 .. N - 1`` in turn, ``gamma_i`` from
    ``p(a) ∝ eta_i(a) [a <= 1 or no other track holds a]`` by inverting its cumulative sum with
    ``uniforms[g - 1, i]`` (the smallest ``a`` with ``cum_a > u cum_last``); a track with no possible
    choice keeps its value. Each sweep visits only the live tracks, in slot order, with their own
    draws (an empty slot's only choice is ``0``), so its length is the number of live tracks.

    Args:
        log_eta: ``(N, A)`` the joint costs, ``A = M + 2``.
        live: ``(N,)`` bool.
        uniforms: ``(G - 1, N)`` in ``[0, 1)``.
    """
    N, A = log_eta.shape
    G = uniforms.shape[0] + 1
    start = jnp.where(live, 1, 0).astype(jnp.int32)
    counts0 = jnp.zeros(A, jnp.int32).at[start].add(1)
    choices = jnp.arange(A)
    log_eta = jax.lax.stop_gradient(log_eta)

    def track(i, carry):
        gamma, counts, u = carry
        counts = counts.at[gamma[i]].add(-1)
        taken = (choices >= 2) & (counts > 0)
        logits = jnp.where(taken, -jnp.inf, log_eta[i])
        top = jnp.max(logits)
        possible = top > -jnp.inf
        p = jnp.exp(logits - jnp.where(possible, top, 0.0))
        cum = jnp.cumsum(p)
        a = jnp.argmax(cum > u[i] * cum[-1]).astype(jnp.int32)
        new = jnp.where(possible, a, gamma[i])
        return gamma.at[i].set(new), counts.at[new].add(1), u

    live_first = jnp.argsort(~live, stable=True).astype(jnp.int32)  # live slots first, in slot order
    n_live = jnp.sum(live.astype(jnp.int32))

    def row(gamma_counts, u):
        gamma, counts = gamma_counts
        gamma, counts, _ = jax.lax.fori_loop(
            0, n_live, lambda k, c: track(live_first[k], c), (gamma, counts, u)
        )
        return (gamma, counts), gamma

    _, rows = jax.lax.scan(row, (start, counts0), uniforms)
    return jnp.concatenate([start[None, :], rows.reshape(G - 1, N)], axis=0)


def distinct_rows(samples: Array) -> Array:
    """``(G,)`` bool: row ``g`` is the first occurrence of its value (one stable lexicographic sort)."""
    G, N = samples.shape
    keys = tuple(samples[:, i] for i in reversed(range(N)))  # lexsort: the last key is the primary
    order = jnp.lexsort(keys) if N > 0 else jnp.arange(G)
    sorted_rows = samples[order]
    new = jnp.concatenate([jnp.ones((1,), bool), jnp.any(sorted_rows[1:] != sorted_rows[:-1], axis=1)])
    return jnp.zeros(G, bool).at[order].set(new)


def hypothesis_marginals(
    log_eta: Array, samples: Array, distinct: Array
) -> tuple[Array, Array, Array, Array]:
    """The drawn hypotheses weighted exactly and renormalised (steps 4-5 of the reference's spec).

    Args:
        log_eta: ``(N, M + 2)`` the joint costs. samples: ``(G, N)`` the Gibbs rows.
        distinct: ``(G,)`` bool, the rows that count (:func:`distinct_rows`).

    Returns:
        ``(weights (G,), r' (N,), beta (N, M + 1), log_norm ())`` with
        ``log_norm = log sum_{distinct g} prod_i eta_i(gamma_gi)``; all zero (``log_norm = -inf``) when
        no distinct row has a positive weight.
    """
    dtype = log_eta.dtype
    log_w = jnp.sum(jnp.take_along_axis(log_eta, samples.T, axis=1), axis=0)  # (G,)
    log_w = jnp.where(distinct, log_w, -jnp.inf)
    top = jnp.max(log_w)
    feasible = top > -jnp.inf
    top_safe = jnp.where(feasible, top, 0.0)
    log_norm = jnp.where(feasible, top_safe + jnp.log(jnp.sum(jnp.exp(log_w - top_safe))), -jnp.inf)
    weights = jnp.where(feasible & distinct, jnp.exp(log_w - jnp.where(feasible, log_norm, 0.0)), 0.0)
    G, N = samples.shape
    column = jnp.where(samples >= 1, samples - 1, log_eta.shape[1])  # choice 0 (no track): dropped
    tracks = jnp.broadcast_to(jnp.arange(N), (G, N))
    beta = (
        jnp.zeros((N, log_eta.shape[1] - 1), dtype)
        .at[tracks, column]
        .add(jnp.broadcast_to(weights[:, None], (G, N)), mode="drop")
    )
    return weights, jnp.sum(beta, axis=1), beta, log_norm


def gibbs_uniforms(key: PRNGKey, n_rows: int, n_tracks: int, dtype: Any) -> Array:
    """``(n_rows, n_tracks)`` uniforms in ``[0, 1)`` on the grid ``2^-24`` (exact in float32 and
    float64, so runs in either precision draw the same numbers): the sampler's draws of an update."""
    bits = jax.random.bits(key, (n_rows, n_tracks), jnp.uint32) >> 8
    return bits.astype(dtype) * jnp.asarray(2.0**-24, dtype)
