"""Step 6 of the adaptive Gaussian-sum filter (seed 001, eq 39): pruning and the three merge rules as a
stateful reducer, with the history of every slot's ancestor "before and after a time step".

The filter (:mod:`gmjax.filters.agsf`) carries the :class:`Step6State` and writes each component's
degree of nonlinearity into it before reducing; on its own, :class:`Step6Merge` follows the Reducer
protocol (``init``, ``reduce``, ``__call__``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp

from gmjax import _validate, gaussian
from gmjax import mixture as gmm
from gmjax._loops import bounded_loop
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array, PRNGKey
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction.base import ReductionInfo, make_info
from gmjax.reduction.runnalls import runnalls_cost

__all__ = ["Step6Merge", "Step6State"]


class Step6State(NamedTuple):
    """The per-slot history :class:`Step6Merge` reads (every leaf has a leading slot axis ``K``).

    A filter gives every child (a predicted or split component) its parent's entries, in the same
    slot order as the mixture, and sets :attr:`don` to the DON of each component before reducing.

    Attributes:
        don: ``(K,)`` DON of each slot's component now (at its Step 2; ``inf`` = unknown).
        ancestor: ``(K,)`` int32, the slot of the previous step's posterior the slot descends from.
        ancestor_weight: ``(K,)`` that ancestor's weight (rule 1, "low before").
        ancestor_don: ``(K,)`` that ancestor's DON (rule 3, "low DON before").
        ancestor_cost: ``(K, A)`` the normalised Runnalls bound between the slot's ancestor and each
            of the ``A`` components of the previous posterior (rule 2, "close before"): row
            ``ancestor`` of that posterior's pair-cost matrix.
    """

    don: Array
    ancestor: Array
    ancestor_weight: Array
    ancestor_don: Array
    ancestor_cost: Array


def _pair_costs(w: Array, m: Array, P: Array) -> Array:
    """``(K, K)`` weight-normalised Runnalls bound ``B_ij / (w_i + w_j)`` of merging ``i`` and ``j``
    (:func:`~gmjax.reduction.runnalls.runnalls_cost` with ``normalized=True``), clipped at 0 (rounding)
    and 0 on the diagonal."""
    ld = gaussian.spd_logdet(P)
    c = runnalls_cost(
        w[:, None], m[:, None], P[:, None], w[None], m[None], P[None], ld[:, None], ld[None], normalized=True
    )
    K = w.shape[0]
    return jnp.where(jnp.eye(K, dtype=bool), 0.0, jnp.maximum(c, 0.0))


class _MergeCarry(NamedTuple):
    w: Array  # (K,) working weights
    m: Array  # (K, d)
    P: Array  # (K, d, d)
    mask: Array  # (K,) live working slots
    ancestor: Array  # (K,) ancestor slot (of the heavier member for a merged slot)
    ancestor_cost: Array  # (K, A) the ancestor's row of the previous pair costs
    low_before: Array  # (K,) rule 1's history half
    low_don: Array  # (K,) rule 3 (now and before)
    don: Array  # (K,) DON now (the larger of a merged pair's)
    slot: Array  # (K_in,) working slot of every input slot (-1: pruned / padded)
    n_merged: Array  # ()
    cost: Array  # () summed Runnalls bound of the merges


def _merge_rules(merge: Step6Merge, carry: _MergeCarry) -> _MergeCarry:
    """Greedy pairwise merging under rules 1–3 (see :class:`Step6Merge`), at most ``K - 1`` merges."""
    K = carry.w.shape[0]
    ar = jnp.arange(K)
    upper = ar[:, None] < ar[None, :]
    eye = jnp.eye(carry.m.shape[-1], dtype=carry.P.dtype)

    def body(c: _MergeCarry):
        cost = _pair_costs(c.w, c.m, c.P)
        same = c.ancestor[:, None] == c.ancestor[None, :]
        before = jnp.where(same, 0.0, c.ancestor_cost[:, c.ancestor])
        low = (c.w < merge.low_weight) & c.low_before
        rule1 = low[:, None] & low[None, :]
        rule2 = (cost < merge.merge_threshold) & (before < merge.merge_threshold)
        rule3 = c.low_don[:, None] & c.low_don[None, :]
        elig = (rule1 | rule2 | rule3) & upper & c.mask[:, None] & c.mask[None, :]
        flat = jnp.where(elig, cost, jnp.inf).reshape(-1)
        k = jnp.argmin(flat)
        do = jnp.isfinite(flat[k])
        i, j = k // K, k % K
        W, mm, PP = gaussian.moment_merge_pair(c.w[i], c.m[i], c.P[i], c.w[j], c.m[j], c.P[j])
        at_i = (ar == i) & do
        at_j = (ar == j) & do
        heavier = jnp.where(c.w[j] > c.w[i], j, i)
        return _MergeCarry(
            w=jnp.where(at_i, W, jnp.where(at_j, 0.0, c.w)),
            m=jnp.where(at_i[:, None], mm, jnp.where(at_j[:, None], 0.0, c.m)),
            P=jnp.where(at_i[:, None, None], PP, jnp.where(at_j[:, None, None], eye, c.P)),
            mask=c.mask & ~at_j,
            ancestor=jnp.where(at_i, c.ancestor[heavier], c.ancestor),
            ancestor_cost=jnp.where(at_i[:, None], c.ancestor_cost[heavier], c.ancestor_cost),
            low_before=jnp.where(at_i, c.low_before[i] & c.low_before[j], c.low_before),
            low_don=jnp.where(at_i, c.low_don[i] & c.low_don[j], c.low_don),
            don=jnp.where(at_i, jnp.maximum(c.don[i], c.don[j]), c.don),
            slot=jnp.where(do & (c.slot == j), i.astype(jnp.int32), c.slot),
            n_merged=c.n_merged + do.astype(jnp.int32),
            cost=c.cost + jnp.where(do, W * jnp.where(do, flat[k], 0.0), 0.0),
        ), do

    return bounded_loop(K - 1, body, carry)


def _fit(c: _MergeCarry, capacity: int):
    """Keep the live slots (in order) in ``capacity`` slots; the heaviest if too many. Renormalised.

    Returns:
        ``(gm, don (capacity,), overflow, labels (K_in,))``: ``labels`` maps every input slot to
        its output slot (``-1``: pruned, padded or dropped by the overflow).
    """
    K = c.w.shape[0]
    n_out = min(capacity, K)
    n_live = jnp.sum(c.mask.astype(jnp.int32))
    overflow = n_live > capacity
    order_keep = _util.live_first(c.mask)[0][:n_out]
    order_top, _ = gmm.heaviest_slots(c.w, c.mask, n_out)
    idx = jnp.where(overflow, order_top, order_keep)
    live = c.mask[idx]
    gm = gmm.sanitize(GaussianMixture(jnp.where(live, c.w[idx], 0.0), c.m[idx], c.P[idx], live))
    gm = gmm.pad(gmm.normalize(gm), capacity)
    don = jnp.concatenate(
        [jnp.where(live, c.don[idx], jnp.inf), jnp.full((capacity - n_out,), jnp.inf, c.don.dtype)]
    )
    out_slot = (
        jnp.full((K,), -1, jnp.int32).at[idx].set(jnp.where(live, jnp.arange(n_out, dtype=jnp.int32), -1))
    )
    labels = jnp.where(c.slot >= 0, out_slot[jnp.clip(c.slot, 0, K - 1)], -1)
    return gm, don, overflow, labels


@pytree_dataclass
class Step6Merge:
    """Step 6 of seed 001 (pruning and the three merge rules, eq 39) as a stateful reducer.

    A :class:`~gmjax.reduction.Reducer`: ``init(capacity) -> Step6State``, ``reduce(gm, state, *,
    key) -> (gm, state, ReductionInfo)`` and ``Step6Merge()(gm)`` (from a fresh state). The
    :class:`Step6State` holds, per input slot, the component's DON now and the history of its
    ancestor at the previous step ("before and after a time step", see the module docstring).

    1. *Pruning*: components with weight ``< prune_threshold`` are dropped (the heaviest is always
       kept) and the weights renormalised.
    2. *Rule 1* (low weight): a component is *low* when its weight is ``< low_weight`` now and its
       ancestor's weight was ``< low_weight``; two low components are merged. A merged pair stays
       low only while its summed weight is ``< low_weight`` ("merged gradually").
    3. *Rule 2* (closely approximate a Gaussian): the pair's weight-normalised Runnalls bound
       ``B_ij / (w_i + w_j)`` (the KL cost of replacing the pair by its moment-matched Gaussian) is
       ``< merge_threshold`` now, and so was their ancestors' (0 for two descendants of one
       ancestor, which *was* one Gaussian).
    4. *Rule 3* (low nonlinearity): both components have DON ``< merge_don`` now and their
       ancestors had DON ``< merge_don``. The paper's threshold is ``0.2 psi_th = 0.004``; it is
       its own field so that ``psi_th = inf`` switches off splitting only (a merged component's
       DON is the larger of the pair's).

    Eligible pairs are merged greedily, cheapest (smallest normalised Runnalls bound) first, with
    the moment-preserving merge of eq 39 (eq 39 as printed omits the division by
    ``alpha_j + alpha_j'`` that makes it moment-preserving; we divide), until no eligible pair
    remains; a merged slot takes the history of its heavier member. The live components are then
    fitted, in slot order, to ``capacity`` output slots (the heaviest when more survive:
    ``info.overflow``) and renormalised.

    **State contract.** The new state describes the output: each output component is its own
    ancestor (:meth:`history`), with its DON. The filter gives every child its parent's entries
    and sets ``state.don`` to the current DON before the next call. A fresh state (:meth:`init`)
    has no history: the "before" halves of rules 1–3 count as met and the DON is unknown
    (``inf``, rule 3 off), so ``Step6Merge()(gm)`` prunes and merges by rules 1–2 on ``gm`` alone.

    Attributes:
        prune_threshold, low_weight, merge_threshold, merge_don: the thresholds (leaves; see
            :class:`~gmjax.filters.agsf.AGSFConfig`).
        capacity: static output slots (default ``None``: the input's).

    ``info.cost`` is the summed (unnormalised) Runnalls bound of the merges, ``info.pruned_mass``
    the weight removed by pruning, and ``info.aux = {"n_pruned", "n_merged"}``.
    """

    prune_threshold: Any = 1e-4
    low_weight: Any = 0.01
    merge_threshold: Any = 0.1
    merge_don: Any = 0.004
    capacity: int | None = static_field(None)

    def init(self, capacity: int) -> Step6State:
        """A fresh state (no history) for mixtures of ``capacity`` slots."""
        zeros = jnp.zeros((capacity,))
        return Step6State(
            don=jnp.full((capacity,), jnp.inf),
            ancestor=jnp.arange(capacity, dtype=jnp.int32),
            ancestor_weight=zeros,
            ancestor_don=zeros,
            ancestor_cost=jnp.zeros((capacity, capacity)),
        )

    def history(self, gm: GaussianMixture, don: Array | None = None) -> Step6State:
        """The state that names ``gm`` as the previous step's posterior (each slot its own ancestor).

        Args:
            gm: the posterior, capacity ``K``.
            don: ``(K,)`` DON of each component (default ``inf``: unknown, e.g. a prior).
        """
        K = gm.capacity
        dtype = gm.weights.dtype
        don = jnp.full((K,), jnp.inf, dtype) if don is None else jnp.asarray(don, dtype)
        return Step6State(
            don=don,
            ancestor=jnp.arange(K, dtype=jnp.int32),
            ancestor_weight=gm.weights,
            ancestor_don=don,
            ancestor_cost=_pair_costs(gm.weights, gm.means, gm.covs),
        )

    def _check(self, gm: GaussianMixture, state: Step6State) -> None:
        for name in ("prune_threshold", "low_weight", "merge_threshold", "merge_don"):
            _validate.validate_nonneg(getattr(self, name), name)
        _validate.validate_capacity(self.capacity, gm)
        if not isinstance(state, Step6State):
            raise ValueError(f"state: expected a Step6State, got {type(state).__name__}")
        K = gm.capacity
        for name, leaf in zip(Step6State._fields, state):
            if jnp.shape(leaf)[:1] != (K,):
                raise ValueError(
                    f"state.{name}: expected a leading slot axis of length {K}, got shape {jnp.shape(leaf)}"
                )

    def reduce(
        self, gm: GaussianMixture, state: Step6State, *, key: PRNGKey | None = None
    ) -> tuple[GaussianMixture, Step6State, ReductionInfo]:
        """Prune, merge by rules 1–3 and fit to ``capacity``: ``(reduced, new_state, info)``."""
        del key
        self._check(gm, state)
        K = gm.capacity
        cap = K if self.capacity is None else int(self.capacity)
        w = gm.weights
        heaviest = jnp.arange(K) == jnp.argmax(jnp.where(gm.mask, w, -jnp.inf))
        keep = gm.mask & ((w >= self.prune_threshold) | heaviest)
        pruned_mass = jnp.sum(jnp.where(gm.mask & ~keep, w, 0.0))
        w = jnp.where(keep, w, 0.0)
        w = w / jnp.sum(w)
        eye = jnp.eye(gm.dim, dtype=gm.covs.dtype)
        dtype = gm.weights.dtype
        carry = _MergeCarry(
            w=w,
            m=jnp.where(keep[:, None], gm.means, 0.0),
            P=jnp.where(keep[:, None, None], gm.covs, eye),
            mask=keep,
            ancestor=jnp.asarray(state.ancestor, jnp.int32),
            ancestor_cost=jnp.asarray(state.ancestor_cost, dtype),
            low_before=state.ancestor_weight < self.low_weight,
            low_don=(state.don < self.merge_don) & (state.ancestor_don < self.merge_don),
            don=jnp.asarray(state.don, dtype),
            slot=jnp.where(keep, jnp.arange(K, dtype=jnp.int32), -1),
            n_merged=jnp.zeros((), jnp.int32),
            cost=jnp.zeros((), dtype),
        )
        merged = _merge_rules(self, carry)
        out, don, overflow, labels = _fit(merged, cap)
        aux = {"n_pruned": jnp.sum((gm.mask & ~keep).astype(jnp.int32)), "n_merged": merged.n_merged}
        info = make_info(
            gm, out, labels, pruned_mass=pruned_mass, overflow=overflow, cost=merged.cost, aux=aux
        )
        return out, self.history(out, don), info

    def __call__(
        self, gm: GaussianMixture, *, key: PRNGKey | None = None
    ) -> tuple[GaussianMixture, ReductionInfo]:
        """The reduction from a fresh state (:meth:`init`): ``(reduced, info)``."""
        out, _, info = self.reduce(gm, self.init(gm.capacity), key=key)
        return out, info
