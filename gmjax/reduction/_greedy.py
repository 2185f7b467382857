"""The greedy pairwise-merge engine shared by Runnalls, Salmond and West (and GMRC's start).

All three repeatedly merge one pair with the moment-preserving merge (seed 002 eqs 70–72) until
``num_out`` components remain or the selected pair's cost exceeds ``threshold``. The loop is a
``lax.fori_loop`` with the static trip count ``K - num_out`` and a "done" flag, so it runs under
``jit``/``vmap`` and is reverse-mode differentiable (the threshold's gradient is 0 almost
everywhere, but finite).

Conventions shared with the NumPy references in ``references/reduction_np.py``:

* The merged component of the pair ``(i, j)`` goes to slot ``i`` and slot ``j`` is emptied. For
  Runnalls and Salmond ``i < j`` is the first minimiser of the cost over the upper triangle in
  row-major slot order; for West ``i`` is the (first) smallest-weight slot and ``j`` its nearest
  neighbour (first minimiser).
* Merging continues while the selected cost is ``<= threshold`` (``threshold = inf``: to the count).
* ``info.aux["merges"]`` is the ``(K - num_out, 2)`` merge sequence in input slot indices (``-1``
  rows after the last merge), ``info.cost`` the sum of the selected costs.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._types import Array
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction.base import make_info

# ----------------------------------------------------------------------------- the greedy loop


class GreedyState(NamedTuple):
    w: jax.Array
    m: jax.Array
    P: jax.Array
    mask: jax.Array
    labels: jax.Array
    C: jax.Array
    lb: jax.Array
    merges: jax.Array
    total: jax.Array
    n_live: jax.Array
    logdet: jax.Array | None = None  # (K,) log det P per slot, kept current when a row cost reads it


def greedy_steps(gm, num_out, threshold, select, row_cost):
    """Run ``K - num_out`` guarded merge steps.

    ``select(state) -> (i, j, cost)``; ``row_cost(state, i) -> (K,)`` costs of the new slot ``i``
    against every slot (or None when ``select`` does not use the cost matrix).

    The pair-cost matrix ``C`` is kept "clean" (``+inf`` on and below the diagonal and in the rows
    and columns of dead slots) together with ``lb``, a lower bound of every row minimum, so a step
    costs ``O(K)`` instead of ``O(K^2)`` (see :func:`upper_argmin`): after a merge only row ``i``
    and column ``i`` change (``lb`` lowered where column ``i`` decreased) and row/column ``j`` die.
    """
    K = gm.capacity
    n_steps = K - num_out
    d = gm.dim
    eye = jnp.eye(d, dtype=gm.covs.dtype)
    ar = jnp.arange(K)
    threshold = jax.lax.stop_gradient(threshold)

    def body(step, s):
        i, j, c, lb = select(s)
        do = (s.n_live > num_out) & (c <= threshold) & jnp.isfinite(c)
        W, mm, PP = gaussian.moment_merge_pair(s.w[i], s.m[i], s.P[i], s.w[j], s.m[j], s.P[j])
        at_i = (ar == i) & do
        at_j = (ar == j) & do
        w = jnp.where(at_i, W, jnp.where(at_j, 0.0, s.w))
        m = jnp.where(at_i[:, None], mm, jnp.where(at_j[:, None], 0.0, s.m))
        P = jnp.where(at_i[:, None, None], PP, jnp.where(at_j[:, None, None], eye, s.P))
        mask = s.mask & ~at_j
        labels = jnp.where(do & (s.labels == j), i, s.labels)
        logdet = None if s.logdet is None else jnp.where(at_i, gaussian.spd_logdet(PP), s.logdet)
        C = s.C
        if row_cost is not None:
            s2 = s._replace(w=w, m=m, P=P, mask=mask, logdet=logdet)
            row = jnp.where(mask & (ar != i), row_cost(s2, i), jnp.inf)
            row_up = jnp.where(ar > i, row, jnp.inf)  # C[i, k], k > i
            col_lo = jnp.where(ar < i, row, jnp.inf)  # C[k, i], k < i
            # out-of-range index + mode="drop" when no merge happens: pure in-place writes
            ii = jnp.where(do, i, K)
            jj = jnp.where(do, j, K)
            inf_row = jnp.full((K,), jnp.inf, C.dtype)
            C = C.at[ii, :].set(row_up, mode="drop").at[:, ii].set(col_lo, mode="drop")
            C = C.at[jj, :].set(inf_row, mode="drop").at[:, jj].set(inf_row, mode="drop")
            lb = jnp.where(do, jnp.minimum(lb, col_lo), lb)
            lb = jnp.where(at_i, jnp.min(row_up), jnp.where(at_j, jnp.inf, lb))
        merges = s.merges.at[step].set(jnp.where(do, jnp.stack([i, j]), -1).astype(jnp.int32))
        return GreedyState(
            w,
            m,
            P,
            mask,
            labels,
            C,
            lb,
            merges,
            s.total + jnp.where(do, c, 0.0),
            s.n_live - do.astype(jnp.int32),
            logdet,
        )

    return body, n_steps


def clean_upper(C, mask):
    K = C.shape[0]
    upper = jnp.arange(K)[:, None] < jnp.arange(K)[None, :]
    return jnp.where(upper & mask[:, None] & mask[None, :], C, jnp.inf)


def upper_argmin(s: GreedyState):
    """The first minimiser of ``C`` in row-major order, from the row lower bounds ``lb``.

    Repeatedly take the row with the smallest bound (lowest index on ties) and tighten its bound to
    the true row minimum; once the chosen row's bound is tight it is the global minimum, and no
    row before it can hold an equal value (its bound would be <= and it would have been chosen),
    so the result equals ``argmin(C.reshape(-1))``. A ``while_loop`` (at most ``K + 1`` rounds);
    returns ``(i, j, cost, lb)``.
    """
    K = s.w.shape[0]
    cost_matrix = s.C

    def cond(c):
        _, _, tight, n = c
        return (~tight) & (n <= K)

    def body(c):
        lb, _, _, n = c
        i = jnp.argmin(lb)
        true = jnp.min(s.C[i, :])
        tight = (true == lb[i]) | jnp.isinf(lb[i])
        return lb.at[i].set(true), i.astype(jnp.int32), tight, n + 1

    # the search only picks indices: it runs on stopped values (a while_loop is not reverse-mode
    # differentiable), and the selected cost is read from the differentiable matrix afterwards
    C = jax.lax.stop_gradient(s.C)
    s = s._replace(C=C)
    lb, i, _, _ = jax.lax.while_loop(
        cond,
        body,
        (jax.lax.stop_gradient(s.lb), jnp.zeros((), jnp.int32), jnp.asarray(False), jnp.zeros((), jnp.int32)),
    )
    j = jnp.argmin(C[i, :]).astype(jnp.int32)
    return i, j, cost_matrix[i, j], lb


def init_state(gm, C, logdet=None):
    """The loop's start; ``logdet`` ``(K,)``: each slot's ``log det P``, carried and updated for the
    merged slot only (a row cost then reads ``state.logdet`` instead of recomputing every slot's)."""
    K = gm.capacity
    n_steps = K
    w = jnp.where(gm.mask, gm.weights, 0.0)
    return GreedyState(
        w,
        gm.means,
        gm.covs,
        gm.mask,
        _util.identity_labels(gm),
        C,
        jnp.min(C, axis=1),
        jnp.full((max(n_steps, 1), 2), -1, jnp.int32),
        jnp.zeros((), w.dtype),
        jnp.sum(gm.mask.astype(jnp.int32)),
        logdet,
    )


def finish(gm, s, n_steps, capacity):
    work = GaussianMixture(s.w, s.m, s.P, s.mask)
    out, labels, overflow, dropped = _util.finalize(gm, work, s.labels, capacity)
    aux = {"merges": s.merges[:n_steps]}
    return out, make_info(gm, out, labels, pruned_mass=dropped, overflow=overflow, cost=s.total, aux=aux)


def sequential(core):
    """Batch ``core`` under ``vmap`` as a sequential ``lax.map`` (``custom_batching``).

    The O(K)-per-step greedy loop updates single rows and columns of the cost matrix in place;
    a vmapped version turns these into batched scatters over ``(B, K, K)`` and runs several times
    slower than mapping the per-mixture kernel over the batch.

    A ``custom_vmap`` has no differentiation rule, so the sequential kernel is wrapped in a
    ``custom_jvp`` whose rule differentiates ``core`` itself: ``jax.grad`` / ``jax.jacfwd`` work
    (under ``vmap`` the derivative runs batched, the value sequentially).
    """
    seq = jax.custom_batching.sequential_vmap(core)
    fn = jax.custom_jvp(lambda *args: seq(*args))

    def jvp(primals, tangents):
        out, out_dot = jax.jvp(core, primals, tangents)
        zero = _zero_of(primals)
        return _tied(out, zero), _tied(out_dot, zero)

    fn.defjvp(jvp)
    return fn


def _zero_of(tree) -> Array:
    """A scalar ``0.0`` that depends on every array leaf of ``tree`` (NaN-safe: a ``where``, not ``0 *``).

    Under ``vmap`` the sequential kernel returns every output batched; an output of ``core`` that
    does not depend on a batched input (a threshold passed through, a constant) comes back from
    ``jax.jvp(core)`` unbatched, and ``jit`` then fails with an ``IndexError`` when it batches the
    linearised program. Adding this zero batches such outputs as the primal rule does.
    """
    zero = jnp.zeros(())
    for leaf in jax.tree_util.tree_leaves(tree):
        if jnp.size(leaf) and jnp.issubdtype(jnp.result_type(leaf), jnp.number):
            zero = zero + jnp.where(False, jnp.ravel(leaf)[0], 0).astype(zero.dtype)
    return zero


def _tied(tree, zero: Array):
    def tie(x):
        dtype = jnp.result_type(x)
        if dtype == jax.dtypes.float0:
            return x
        if dtype == jnp.bool_:
            return x | (zero != 0)
        return x + zero.astype(dtype)

    return jax.tree_util.tree_map(tie, tree)
