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
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util

# ----------------------------------------------------------------------------- the greedy loop


class GreedyState(NamedTuple):
    w: jax.Array
    m: jax.Array
    P: jax.Array
    mask: jax.Array
    labels: jax.Array
    C: jax.Array
    merges: jax.Array
    total: jax.Array
    n_live: jax.Array
    logdet: jax.Array | None = None  # (K,) log det P per slot, kept current when a row cost reads it
    Pinv: jax.Array | None = None  # (K, d, d) P^{-1} per slot, kept current when a selection reads it


def greedy_steps(gm, num_out, threshold, select, row_cost):
    """Run ``K - num_out`` guarded merge steps.

    ``select(state) -> (i, j, cost)``; ``row_cost(state, i) -> (K,)`` costs of the new slot ``i``
    against every slot (or None when ``select`` does not use the cost matrix).

    The pair-cost matrix ``C`` is kept "clean" (``+inf`` on and below the diagonal and in the rows
    and columns of dead slots): after a merge only row ``i`` and column ``i`` are recomputed
    (``O(K)`` costs) and row/column ``j`` die; the selection (:func:`upper_argmin`) reads ``C``.
    """
    K = gm.capacity
    n_steps = K - num_out
    d = gm.dim
    eye = jnp.eye(d, dtype=gm.covs.dtype)
    ar = jnp.arange(K)
    threshold = jax.lax.stop_gradient(threshold)

    def body(step, s):
        i, j, c = select(s)
        do = (s.n_live > num_out) & (c <= threshold) & jnp.isfinite(c)
        W, mm, PP = gaussian.moment_merge_pair(s.w[i], s.m[i], s.P[i], s.w[j], s.m[j], s.P[j])
        at_i = (ar == i) & do
        at_j = (ar == j) & do
        # two row writes (an out-of-range index and mode="drop" when no merge happens), not
        # whole-array selects: O(d^2) per step instead of O(K d^2)
        ii = jnp.where(do, i, K)
        jj = jnp.where(do, j, K)
        w = s.w.at[ii].set(W, mode="drop").at[jj].set(0.0, mode="drop")
        m = s.m.at[ii].set(mm, mode="drop").at[jj].set(0.0, mode="drop")
        P = s.P.at[ii].set(PP, mode="drop").at[jj].set(eye, mode="drop")
        mask = s.mask & ~at_j
        labels = jnp.where(do & (s.labels == j), i, s.labels)
        logdet = None if s.logdet is None else jnp.where(at_i, gaussian.spd_logdet(PP), s.logdet)
        Pinv = None if s.Pinv is None else s.Pinv.at[ii].set(gaussian.spd_inv(PP), mode="drop")
        C = s.C
        if row_cost is not None:
            s2 = s._replace(w=w, m=m, P=P, mask=mask, logdet=logdet)
            row = jnp.where(mask & (ar != i), row_cost(s2, i), jnp.inf)
            row_up = jnp.where(ar > i, row, jnp.inf)  # C[i, k], k > i
            col_lo = jnp.where(ar < i, row, jnp.inf)  # C[k, i], k < i
            inf_row = jnp.full((K,), jnp.inf, C.dtype)
            C = C.at[ii, :].set(row_up, mode="drop").at[:, ii].set(col_lo, mode="drop")
            C = C.at[jj, :].set(inf_row, mode="drop").at[:, jj].set(inf_row, mode="drop")
        merges = s.merges.at[step].set(jnp.where(do, jnp.stack([i, j]), -1).astype(jnp.int32))
        return GreedyState(
            w,
            m,
            P,
            mask,
            labels,
            C,
            merges,
            s.total + jnp.where(do, c, 0.0),
            s.n_live - do.astype(jnp.int32),
            logdet,
            Pinv,
        )

    return body, n_steps


def clean_upper(C, mask):
    K = C.shape[0]
    upper = jnp.arange(K)[:, None] < jnp.arange(K)[None, :]
    return jnp.where(upper & mask[:, None] & mask[None, :], C, jnp.inf)


def upper_argmin(s: GreedyState):
    """The first minimiser of ``C`` in row-major order, ``(i, j, cost)``: the first row with the
    smallest row minimum, then that row's first minimiser, so the result equals
    ``argmin(C.reshape(-1))``.

    The row minima are one plain ``min`` reduction over ``C`` (``O(K^2)``, vectorised); under
    ``vmap`` over a batch of mixtures this is several times faster than tracking lower bounds of
    the row minima with a ``while_loop`` (which runs until the slowest mixture of the batch is
    done; ``benchmarks/results/reducer_limit.md``). The search runs on stopped values (it only
    picks indices); the selected cost is read from the differentiable matrix.
    """
    C = jax.lax.stop_gradient(s.C)
    i = jnp.argmin(jnp.min(C, axis=1)).astype(jnp.int32)
    j = jnp.argmin(C[i, :]).astype(jnp.int32)
    return i, j, s.C[i, j]


def init_state(gm, C, logdet=None, Pinv=None):
    """The loop's start; ``logdet`` ``(K,)`` / ``Pinv`` ``(K, d, d)``: each slot's ``log det P`` /
    ``P^{-1}``, carried and updated for the merged slot only (a row cost or a selection then reads
    them instead of recomputing every slot's)."""
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
        jnp.full((max(n_steps, 1), 2), -1, jnp.int32),
        jnp.zeros((), w.dtype),
        jnp.sum(gm.mask.astype(jnp.int32)),
        logdet,
        Pinv,
    )


def finish(gm, s, n_steps, capacity):
    work = GaussianMixture(s.w, s.m, s.P, s.mask)
    return _util.finalize_info(gm, work, s.labels, capacity, cost=s.total, aux={"merges": s.merges[:n_steps]})


# ----------------------------------------------------------------------------- batching

BLOCK = 32
"""Mixtures per vectorised block of :func:`chunked` (Runnalls for ``d >= 3``, Salmond)."""


def chunked(core, batch_size: int | None):
    """``core`` that runs under ``vmap`` in blocks of ``batch_size`` mixtures (``custom_batching``):
    a ``lax.map`` over blocks of a vmapped ``core`` (the same per-mixture program as the plain vmap,
    same values; a batch of at most one block is one plain vmap); ``None``: ``core`` itself.

    Each merge step reads and writes the batch's whole working set (cost matrices, covariances,
    the row cost's intermediates); over a large batch it leaves the cache, and the plain vmap of
    the loop can be several times slower than the same loop in blocks. Which is faster is measured,
    not derived (``bench_reducer_limit.py``, ``bench_cost_model.py``): blocks for Runnalls at
    ``d >= 3`` (1000 mixtures 60 -> 20 at d = 4: 1.3x; the R-GSF of the cost model at d = 4:
    2.3x) and for Salmond at every ``d`` (1.2-2x); the plain vmap for Runnalls at ``d <= 2`` (the
    R-GSF at d = 1 is 1.25x slower in blocks) and for West.

    A ``custom_vmap`` has no differentiation rule, so the kernel is wrapped in a ``custom_jvp``
    whose rule differentiates ``core`` itself: ``jax.grad`` / ``jax.jacfwd`` work (under ``vmap``
    the derivative runs as a plain vmap, the value in blocks).
    """
    if batch_size is None:
        return core

    @jax.custom_batching.custom_vmap
    def blocked(*args):
        return core(*args)

    @blocked.def_vmap
    def _rule(axis_size, in_batched, *args):
        leaves, tree = jax.tree_util.tree_flatten(args)
        flags = jax.tree_util.tree_leaves(in_batched)

        def one(batched):
            it = iter(batched)
            return core(*tree.unflatten([next(it) if b else x for x, b in zip(leaves, flags)]))

        out = _map_in_blocks(one, [x for x, b in zip(leaves, flags) if b], axis_size, batch_size)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    fn = jax.custom_jvp(lambda *args: blocked(*args))

    def jvp(primals, tangents):
        out, out_dot = jax.jvp(core, primals, tangents)
        zero = _zero_of(primals)
        return _tied(out, zero), _tied(out_dot, zero)

    fn.defjvp(jvp)
    return fn


def _map_in_blocks(f, xs, n: int, batch_size: int):
    """``vmap(f)(xs)`` over the leading axis ``n``, computed as a ``lax.map`` over blocks of
    ``batch_size``; the last block is filled up with copies of the first entry (discarded), so
    one block program is compiled, not a second one for a remainder. (Not ``lax.map(...,
    batch_size=)``: it compiles the remainder apart and its inferred reshape fails on zero-size
    outputs such as an empty merge sequence.)"""
    n_blocks = -(-n // batch_size)
    if n_blocks <= 1:
        return jax.vmap(f)(xs)
    fill = n_blocks * batch_size - n

    def blocks(x):
        x = jnp.concatenate([x, jnp.repeat(x[:1], fill, axis=0)]) if fill else x
        return x.reshape((n_blocks, batch_size) + x.shape[1:])

    out = jax.lax.map(jax.vmap(f), jax.tree_util.tree_map(blocks, xs))
    return jax.tree_util.tree_map(lambda y: y.reshape((n_blocks * batch_size,) + y.shape[2:])[:n], out)


def _zero_of(tree) -> jax.Array:
    """A scalar ``0.0`` that depends on every array leaf of ``tree`` (NaN-safe: a ``where``, not ``0 *``).

    Under ``vmap`` the blocked kernel returns every output batched; an output of ``core`` that does
    not depend on a batched input (a threshold passed through, a constant) comes back from
    ``jax.jvp(core)`` unbatched, and ``jit`` then fails with an ``IndexError`` when it batches the
    linearised program. Adding this zero batches such outputs as the primal rule does.
    """
    zero = jnp.zeros(())
    for leaf in jax.tree_util.tree_leaves(tree):
        if jnp.size(leaf) and jnp.issubdtype(jnp.result_type(leaf), jnp.number):
            zero = zero + jnp.where(False, jnp.ravel(leaf)[0], 0).astype(zero.dtype)
    return zero


def _tied(tree, zero: jax.Array):
    def tie(x):
        dtype = jnp.result_type(x)
        if dtype == jax.dtypes.float0:
            return x
        if dtype == jnp.bool_:
            return x | (zero != 0)
        return x + zero.astype(dtype)

    return jax.tree_util.tree_map(tie, tree)
