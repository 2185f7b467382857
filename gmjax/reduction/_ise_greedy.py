"""The state and ISE terms shared by the greedy ISE reductions, Williams and COWA.

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

from typing import NamedTuple

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util


def overlap(ma, Pa, mb, Pb):
    return jnp.exp(gaussian.spd_logpdf(ma, mb, Pa + Pb))


def self_term(gm: GaussianMixture, w0: jax.Array) -> jax.Array:
    """``J_hh = sum_ij w_i w_j N(m_i; m_j, P_i + P_j)`` of the original mixture ``h`` (``w0``: its
    weights, zero on empty slots); constant over the greedy loop."""
    live2 = gm.mask[:, None] & gm.mask[None, :]
    S = jnp.where(live2, overlap(gm.means[:, None], gm.covs[:, None], gm.means[None], gm.covs[None]), 0.0)
    return w0 @ S @ w0


class ISEGreedyState(NamedTuple):
    w: jax.Array
    m: jax.Array
    P: jax.Array
    mask: jax.Array
    labels: jax.Array
    n_live: jax.Array
    cost: jax.Array
    actions: jax.Array


def initial_state(gm: GaussianMixture, w0: jax.Array, n_steps: int) -> ISEGreedyState:
    """The greedy loop's state before any action (shared by Williams and COWA)."""
    return ISEGreedyState(
        w0,
        gm.means,
        gm.covs,
        gm.mask,
        _util.identity_labels(gm),
        jnp.sum(gm.mask.astype(jnp.int32)),
        jnp.zeros((), w0.dtype),
        jnp.full((max(n_steps, 1), 2), -2, jnp.int32),
    )


def ise_terms(s, gm0, w0):
    S = overlap(s.m[:, None], s.P[:, None], s.m[None], s.P[None])
    live2 = s.mask[:, None] & s.mask[None, :]
    S = jnp.where(live2, S, 0.0)
    A = overlap(s.m[:, None], s.P[:, None], gm0.means[None], gm0.covs[None])
    a = jnp.where(s.mask, A @ w0, 0.0)
    return S, a
