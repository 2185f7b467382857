"""Distribution-similarity ("Gauss") clustering of mixture components (seed 000 §III-B, seed 003 §2.1).

Seed 000 is Xu et al., PCM; seed 003 is Xu et al. 2019, GMRCM (docs/references.md).

The clustering of both seeds, written as fixed-size array programs that run under ``jit``/``vmap``:

1. **Confidence distance.** Two components are *similar* when each centre lies inside the other's
   ``σ* = λσ`` confidence range (seed 000 Definition 1 and Assumption 1; seed 003 eq 5). The papers
   are scalar; for ``d > 1`` we read "the ``λσ`` confidence range of component ``i``" as the
   ellipsoid ``{x : (x - u_i)^T P_i^{-1} (x - u_i) <= λ²}`` of its covariance on the clustering
   dimensions (seed 003 speaks of the projection of the ``P*`` confidence surface, ``g_{P*}(x) <= 0``).
   So ``r_ij = 1`` iff ``δ_ij <= s·λ`` with the *similarity threshold*
   ``δ_ij = max(‖u_j - u_i‖_{P_i}, ‖u_i - u_j‖_{P_j})`` (Mahalanobis norms). In one dimension this is
   seed 000 eq 24, ``r_ij = sign(min{d^{σ*}_i - |u_ij|, d^{σ*}_j - |u_ij|})`` with the scope
   ``d^{σ*}_i = s·λσ_i``, and ``sign(0) = +1`` (a centre *on* the boundary counts as inside, as in
   seed 003's ``g <= 0``).

   *Range scale* ``s`` (default ``0.5``): the papers call ``σ* = λσ`` the "confidence range" without
   saying whether it is the interval's half-width or its full width. Read as the half-width
   (``s = 1``), the static cases of seed 000 Tables 2–4 / seed 003 Tables 1–3 cluster far more than
   the papers report (e.g. the unimodal case gives 3, 2, 1, 1 clusters at ``λ = 1…4`` against the
   papers' 4, 3, 3, 2). Read as the full width of an interval centred on the mean (``s = 0.5``) the
   counts of seed 000 Table 3 and seed 003 Tables 2 (with ``triangular``/``absorb``) are reproduced
   exactly and the others differ only where a centre falls exactly on a boundary (``0.5 = 0.5σ``);
   so ``s = 0.5`` is the default, and ``s`` is a parameter (``benchmarks/bench_pcm_static.py``
   reports both).
2. **Cluster formation by rows** (seed 000 eq 25): cluster ``i`` is row ``i`` of the judgment
   matrix. With ``triangular=True`` the upper-triangular judgment matrix of seed 003 eq 4 is used, so
   cluster ``i`` holds ``i`` and the similar components ``j > i`` (seed 003 eq 6).
3. **Combination of identical clusters** (seed 000 §III-B Step 1): of identical rows the one with
   the lowest index is kept.
4. **Pairwise fine-tuning** (seed 000 eqs 26–28 Step 2–3; seed 003 eqs 7–9). Cluster pairs
   ``(i, j)``, ``i < j``, are visited once in lexicographic order (the static
   list of ``K(K-1)/2`` pairs; a bounded ``lax.while_loop`` jumps straight to the next pair that
   shares a component, the others being no-ops, and clusters are rows of bits), each time in the
   *current* state of the clusters:

   * Situation 1, ``C_i ∩ C_j = ∅``: nothing changes.
   * identical clusters (can arise after earlier pairs): combined into ``C_i`` (Step 1 again).
   * Situation 3, one cluster contains the other. ``subset_rule="split"`` (seed 000: "preserve
     ``C^j`` and its complement as independent clusters"): the subset is kept whole and the superset
     keeps only its complement. ``subset_rule="absorb"`` (seed 003 H2, "keep ``Ω^i`` and the
     complement ``(Ω^j)*``" with ``Ω^j ⊆ Ω^i`` as its text says; the complement of the subset
     within the superset's members is empty): the superset keeps everything and the subset is
     emptied. With seed 003's upper-triangular rows, nested rows ``{1,2,3} ⊃ {2,3} ⊃ {3}`` are the
     rule, and "split" would shatter them into singletons, whereas seed 003 Tables 1–3 report
     counts that fall with ``λ``; so ``gmrcm`` uses "absorb" and ``pcm`` uses "split".
   * Situation 2, a partial overlap: all shared components are removed from both clusters (eq 27),
     and each is re-assigned to the renewed cluster whose nearest member centre is closer in
     Euclidean distance on the clustering dimensions (eq 28, seed 003 eq 9); a tie goes to the
     lower-indexed cluster ``i`` (eq 28 uses ``d^{i*m} <= d^{j*m}``). The shared components are
     re-assigned simultaneously against the renewed clusters of eq 27 (one pass of Step 2.1–2.3
     leaves no overlap between the pair, so Step 2.4's repetition is then a no-op).

   Every step only removes memberships and never removes a component from both clusters of a pair,
   and a pair once disjoint stays disjoint; so after the sweep the clusters partition the live
   components (each component keeps at least its own row). The result depends on the visiting order,
   as the papers' Step 3 does; ours is the deterministic lexicographic order of slot indices.
   Transitivity is *not* imposed: ``a~b`` and ``b~c`` do not put ``a`` and ``c`` together unless the
   rows say so.

Clusters are identified by the slot index of the row they came from (the *head*); padded slots have
empty rows and label ``-1``. Extra padded slots change nothing.
"""

from __future__ import annotations

import functools
from functools import partial
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import gaussian
from gmjax._types import Array, ArrayLike, Mask
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util

__all__ = [
    "ClusterResult",
    "similarity_thresholds",
    "centre_distances",
    "judgment_matrix",
    "combine_identical",
    "resolve_overlaps",
    "labels_from_membership",
    "gauss_cluster",
]


class ClusterResult(NamedTuple):
    """Outcome of :func:`gauss_cluster`.

    Attributes:
        labels: ``(K,)`` int32 head slot of each component's cluster; ``-1`` for padded slots.
        membership: ``(K, K)`` bool, ``membership[c, m]`` = component ``m`` is in cluster ``c``
            (rows of non-head slots are empty); the columns of live slots hold exactly one True.
        n_clusters: ``()`` int32, number of non-empty clusters ``N'``.
        judgment: ``(K, K)`` bool judgment matrix (eq 24 / seed 003 eq 4).
    """

    labels: Array
    membership: Array
    n_clusters: Array
    judgment: Array


def _select_dims(gm: GaussianMixture, dims: Sequence[int] | None) -> tuple[Array, Array]:
    if dims is None:
        return gm.means, gm.covs
    idx = np.asarray(tuple(dims), dtype=np.int64)
    return gm.means[:, idx], gm.covs[:, idx][:, :, idx]


def _safe_sqrt(x: Array) -> Array:
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


@partial(jax.jit, static_argnames=("dims",))
def similarity_thresholds(gm: GaussianMixture, dims: Sequence[int] | None = None) -> Array:
    """``(K, K)`` matrix ``δ_ij``: the smallest ``λ`` at which components ``i`` and ``j`` are similar.

    ``δ_ij = max(sqrt((u_j - u_i)^T P_i^{-1} (u_j - u_i)), sqrt((u_i - u_j)^T P_j^{-1} (u_i - u_j)))``
    on the dimensions ``dims`` (all when ``None``); for scalars ``|u_i - u_j| / min(σ_i, σ_j)``.
    ``δ_ii = 0``; entries that involve a padded slot are ``+inf``.

    Args:
        gm: mixture with capacity ``K``.
        dims: static state dimensions to cluster on (seed 000 §IV-D clusters on position only).
    """
    means, covs = _select_dims(gm, dims)
    # maha[i, j] = (u_j - u_i)^T P_i^{-1} (u_j - u_i)
    maha = gaussian.spd_inv_quad(means[None, :, :] - means[:, None, :], covs[:, None])
    sq = jnp.maximum(maha, maha.T)
    live = gm.mask[:, None] & gm.mask[None, :]
    delta = jnp.where(live, _safe_sqrt(jnp.where(live, sq, 0.0)), jnp.inf)
    eye = jnp.eye(gm.capacity, dtype=bool)
    return jnp.where(eye & live, 0.0, delta)


@partial(jax.jit, static_argnames=("dims",))
def centre_distances(gm: GaussianMixture, dims: Sequence[int] | None = None) -> Array:
    """``(K, K)`` Euclidean distances between centres on ``dims`` (seed 000 eq 23, used by eq 28)."""
    means, _ = _select_dims(gm, dims)
    diff = means[:, None, :] - means[None, :, :]
    return _safe_sqrt(jnp.sum(diff * diff, axis=-1))


def judgment_matrix(delta: Array, radius: ArrayLike, mask: Mask, *, triangular: bool = False) -> Array:
    """Boolean judgment matrix ``r_ij = [δ_ij <= radius]`` (seed 000 eq 24; seed 003 eqs 4–5).

    Args:
        delta: ``(K, K)`` from :func:`similarity_thresholds`.
        radius: ``()`` scope in units of ``σ``: ``s·λ`` (see the module docstring).
        mask: ``(K,)`` live slots.
        triangular: keep only ``j >= i`` (seed 003's upper-triangular matrix).
    """
    r = (delta <= radius) & mask[:, None] & mask[None, :]
    if triangular:
        K = delta.shape[0]
        r = r & jnp.asarray(np.triu(np.ones((K, K), bool)))
    return r


def combine_identical(membership: Array) -> Array:
    """Empty every row equal to a lower-indexed row (seed 000 §III-B Step 1)."""
    return _unpack(_combine_identical_packed(_pack(membership)), membership.shape[-1])


# Cluster rows are packed as bits of ``uint32`` words, ``(..., K) bool -> (..., W) uint32`` with
# ``W = ceil(K / 32)``: the overlap sweep's set operations are then a few word operations per row.
_BITS = 32


def _pack(rows: Array) -> Array:
    """``(..., K)`` bool -> ``(..., W)`` uint32, component ``m`` is bit ``m % 32`` of word ``m // 32``."""
    K = rows.shape[-1]
    W = -(-K // _BITS)
    padded = jnp.pad(rows, [(0, 0)] * (rows.ndim - 1) + [(0, W * _BITS - K)])
    words = padded.reshape(rows.shape[:-1] + (W, _BITS))
    bit = jnp.left_shift(jnp.uint32(1), jnp.arange(_BITS, dtype=jnp.uint32))
    return jnp.sum(jnp.where(words, bit, jnp.uint32(0)), axis=-1, dtype=jnp.uint32)


def _unpack(words: Array, K: int) -> Array:
    """Inverse of :func:`_pack`: ``(..., W)`` uint32 -> ``(..., K)`` bool."""
    shifts = jnp.arange(_BITS, dtype=jnp.uint32)
    bits = (jnp.right_shift(words[..., None], shifts) & jnp.uint32(1)) == 1
    return bits.reshape(words.shape[:-1] + (words.shape[-1] * _BITS,))[..., :K]


def _shares(a: Array, b: Array) -> Array:
    """Whether packed rows ``a`` and ``b`` (broadcast) have a component in common."""
    return jnp.any((a & b) != 0, axis=-1)


def _next_sharing_pair(rows: Array, i: Array, j: Array) -> tuple[Array, Array, Array]:
    """The first pair ``(i', j') >= (i, j)`` in lexicographic order, ``i' < j'``, whose packed rows
    ``(K, W)`` share a component: ``(found, i', j')``. Pairs in between are Situation 1 (no-ops)."""
    K = rows.shape[0]
    idx = jnp.arange(K, dtype=i.dtype)
    in_row = _shares(rows, rows[i]) & (idx >= j) & (idx > i)
    # later[k] = the union of the rows after k; row k shares with a later row iff rows[k] & later[k]
    after = jax.lax.associative_scan(jnp.bitwise_or, rows, reverse=True, axis=0)
    later = jnp.concatenate([after[1:], jnp.zeros_like(rows[:1])], axis=0)
    has_later = _shares(rows, later) & (idx > i)
    here = jnp.any(in_row)
    i_next = jnp.where(here, i, jnp.argmax(has_later).astype(i.dtype))
    j_next = jnp.where(here, in_row, _shares(rows, rows[i_next]) & (idx > i_next))
    return here | jnp.any(has_later), i_next, jnp.argmax(j_next).astype(i.dtype)


_UNROLL_RANKS = 64  # neighbours counted unrolled up to this capacity, in a fori_loop above


def _nearness_ranks(dist: Array) -> Array:
    """``(K, K)`` ``2 R[k, m]`` with ``R[k, m] = #{l : dist[l, m] < dist[k, m]}``, the rank of ``k``
    among ``m``'s neighbours (ties share a rank), as the smallest unsigned type that holds ``2K``.

    ``R`` is order-preserving column by column (``dist[k, m] <= dist[l, m]`` iff ``R[k, m] <=
    R[l, m]``), so eq 28's comparison of nearest-member distances is a comparison of nearest-member
    ranks, exactly; the free low bit lets :func:`_split_pair` tag the members of ``C_j*`` and find
    both nearest members in one minimum. One byte per entry for ``K < 127`` instead of a distance's
    eight: with the selects below, the 1-D grid sweep of ``bench_reducer_limit``'s draw is about 1.7x
    faster under ``vmap``.
    """
    K = dist.shape[0]
    dtype = jnp.uint8 if K < 127 else (jnp.uint16 if K < 32767 else jnp.uint32)
    two = jnp.asarray(2, dtype)

    def below(l):  # [k, m]: 2 if l is nearer to m than k is, else 0
        return jnp.where(dist[l][None, :] < dist, two, jnp.zeros((), dtype))

    # counted neighbour by neighbour, elementwise (a sort and search, or the (K, K, K) comparison,
    # cost 30-70x as much under vmap at K = 20)
    if K <= _UNROLL_RANKS:
        return functools.reduce(jnp.add, [below(l) for l in range(K)])
    return jax.lax.fori_loop(0, K, lambda l, acc: acc + below(l), jnp.zeros((K, K), dtype))


def _split_pair(rows: Array, i: Array, j: Array, ranks: Array, absorb: bool) -> Array:
    """Fine-tune the sharing pair ``(i, j)`` of packed rows ``(K, W)`` (seed 000 eqs 26–28); see the
    module docstring. ``ranks``: :func:`_nearness_ranks` of the centre distances."""
    K = rows.shape[0]
    ci, cj = rows[i], rows[j]
    ov, ri, rj = ci & cj, ci & ~cj, cj & ~ci  # eq 27: the renewed clusters C_i*, C_j*
    j_in_i = jnp.all(rj == 0)  # C_j ⊆ C_i
    i_in_j = jnp.all(ri == 0)  # C_i ⊆ C_j
    # Situation 2, eq 28: the nearest member of C_i* ∪ C_j* to every component, by 2 R + [in C_j*];
    # it lies in C_i* iff d_i <= d_j (a tie of ranks goes to the lower-indexed cluster i)
    far = jnp.asarray(jnp.iinfo(ranks.dtype).max, ranks.dtype)  # odd: "in C_j*" when nobody is
    in_j = _unpack(rj, K)[:, None].astype(ranks.dtype)
    nearest = jnp.min(jnp.where(_unpack(ri | rj, K)[:, None], ranks | in_j, far), axis=0)
    to_i = ov & _pack((nearest & 1) == 0)
    s2_i, s2_j = ri | to_i, rj | (ov & ~to_i)
    empty = jnp.zeros_like(ci)
    if absorb:  # Situation 3, seed 003 H2: the superset keeps everything
        s3_i = jnp.where(j_in_i, ci, empty)
        s3_j = jnp.where(j_in_i, empty, cj)
    else:  # Situation 3, seed 000: the subset survives, the superset keeps its complement
        s3_i = jnp.where(j_in_i, ri, ci)
        s3_j = jnp.where(j_in_i, cj, rj)
    identical = j_in_i & i_in_j
    new_i = jnp.where(identical, ci, jnp.where(j_in_i | i_in_j, s3_i, s2_i))
    new_j = jnp.where(identical, empty, jnp.where(j_in_i | i_in_j, s3_j, s2_j))
    # rows i and j rewritten by a select (under vmap a scatter at batched rows costs more)
    slot = jnp.arange(K, dtype=i.dtype)[:, None]
    return jnp.where(slot == i, new_i, jnp.where(slot == j, new_j, rows))


@partial(jax.jit, static_argnames=("subset_rule",))
def resolve_overlaps(membership: Array, dist: Array, *, subset_rule: str = "split") -> Array:
    """Turn overlapping row clusters into a partition (seed 000 eqs 26–28 Steps 2–3).

    A stack of clusterings of the same components (one per ``λ`` of a grid, say) is resolved in one
    loop that visits only the sharing pairs of each clustering in turn (a clustering equal to the
    previous one is copied); under ``vmap`` the clusterings of the whole batch are pooled, so the
    loop runs about the batch's mean number of pair splits, not its largest (:func:`_sweep`).

    Args:
        membership: ``(K, K)`` or ``(G, K, K)`` bool, row ``c`` is cluster ``c``.
        dist: ``(K, K)`` Euclidean centre distances (eq 28).
        subset_rule: ``"split"`` (seed 000 Situation 3) or ``"absorb"`` (seed 003 H2).

    Returns:
        ``membership``'s shape, bool, with pairwise-disjoint rows covering the same components.
    """
    absorb = _is_absorb(subset_rule)
    if membership.ndim not in (2, 3):
        raise ValueError(f"membership: expected shape (K, K) or (G, K, K), got {membership.shape}")
    if membership.ndim == 2:
        return resolve_overlaps(membership[None], dist, subset_rule=subset_rule)[0]
    K = membership.shape[-1]
    if K < 2:
        return membership
    return _unpack(_resolve_packed(_pack(membership), dist, absorb), K)


def _is_absorb(subset_rule: str) -> bool:
    """Validate ``subset_rule``; whether it is seed 003's ``"absorb"``."""
    if subset_rule not in ("split", "absorb"):
        raise ValueError(f"subset_rule: expected 'split' or 'absorb', got {subset_rule!r}")
    return subset_rule == "absorb"


def _combine_identical_packed(rows: Array) -> Array:
    """:func:`combine_identical` on packed rows ``(K, W)``."""
    K = rows.shape[0]
    same = jnp.all(rows[:, None, :] == rows[None, :, :], axis=-1)  # (K, K)
    lower = jnp.asarray(np.tril(np.ones((K, K), bool), k=-1))  # j < i
    nonempty = jnp.any(rows != 0, axis=-1)
    dup = jnp.any(same & lower & nonempty[None, :], axis=-1)
    return jnp.where(dup[:, None], jnp.zeros_like(rows), rows)


def _resolve_packed(packed: Array, dist: Array, absorb: bool) -> Array:
    """:func:`resolve_overlaps` on packed rows ``(G, K, W)``: :func:`_sweep` with the nearness ranks
    of ``dist``."""
    return _sweep(packed, _nearness_ranks(dist), absorb)


def _sweep(packed: Array, ranks: Array, absorb: bool) -> Array:
    """The overlap sweep of ``G`` clusterings ``(G, K, W)`` of one mixture (``ranks`` ``(K, K)``).

    A clustering whose rows equal the previous one's (neighbouring grid points often have the same
    judgment matrix: in ``bench_reducer_limit``'s draw 87 % of them at ``d = 4``, 3 % at ``d = 1``)
    is not swept again but takes that one's partition. Alone, one lane sweeps the others in turn
    (:func:`_sweep_lanes`). Under ``vmap`` a lane per mixture would sweep its own clusterings and
    the batch would run as many steps as the mixture with the most pair splits (in the 1-D draw 492
    against a mean of 233); so the batch rule pools the clusterings of all mixtures, and each lane
    takes the next clustering of the pool when it finishes one: about the mean number of steps plus
    the longest single clustering. Every clustering goes through the same integer steps either way,
    so the partitions are identical. No derivative flows through bits and ranks.
    """

    def alone(packed, ranks):
        return _sweep_lanes(packed[None], ranks[None], 1, absorb)[0]

    pooled = jax.custom_batching.custom_vmap(alone)

    @pooled.def_vmap
    def _pooled_lanes(axis_size, in_batched, packed, ranks):
        spread = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + a.shape)  # noqa: E731
        packed, ranks = spread(packed, in_batched[0]), spread(ranks, in_batched[1])
        return _sweep_lanes(packed, ranks, axis_size, absorb), True

    return pooled(*jax.lax.stop_gradient((packed, ranks)))


def _sweep_lanes(packed: Array, ranks: Array, lanes: int, absorb: bool) -> Array:
    """Resolve the clusterings ``(B, G, K, W)`` of ``B`` mixtures (``ranks`` ``(B, K, K)``) with
    ``lanes`` workers: each lane splits the next sharing pair of its clustering
    (:func:`_next_sharing_pair`, :func:`_split_pair`) and, when none is left, takes the next
    clustering not yet started; a clustering equal to its mixture's previous one is copied."""
    B, G, K, W = packed.shape
    n = B * G
    if n == 0 or K < 2:
        return packed
    L = min(lanes, n)
    new_run = jnp.concatenate(
        [jnp.ones((B, 1), bool), jnp.any(packed[:, 1:] != packed[:, :-1], axis=(-2, -1))], 1
    )
    run_start = jax.lax.cummax(jnp.where(new_run, jnp.arange(G), 0), axis=1)  # (B, G)
    todo = _util.first_where(new_run.reshape(n), n)  # the clusterings to sweep, then n
    n_todo = jnp.sum(new_run, dtype=jnp.int32)
    flat = packed.reshape(n, K, W)
    # Each step splits one sharing pair, whose position (i, j) then strictly advances, or moves a
    # lane on to its next clustering: at most n * (K(K-1)/2 + 1) steps in all.
    max_steps = min(n * (K * (K - 1) // 2 + 1), 2**31 - 1)
    split = jax.vmap(partial(_split_pair, absorb=absorb))
    next_pair = jax.vmap(_next_sharing_pair)

    def cond(state):
        _, p, _, _, _, step = state
        return jnp.any(p < n_todo) & (step < max_steps)

    def body(state):
        flat, p, i, j, taken, step = state  # p: each lane's position in ``todo``
        at = todo[jnp.minimum(p, n - 1)]
        rows = jnp.take(flat, at, axis=0, mode="clip")
        found, i, j = next_pair(rows, i, j)
        active = p < n_todo
        rows = split(rows, i, j, jnp.take(ranks, at // G, axis=0, mode="clip"))
        flat = flat.at[jnp.where(active & found, at, n)].set(rows, mode="drop")
        done = active & ~found
        p = jnp.where(done, taken + jnp.cumsum(done, dtype=jnp.int32) - 1, p)
        zero = jnp.zeros_like(i)
        return (
            flat,
            p,
            jnp.where(found, i, zero),
            jnp.where(found, j + 1, zero + 1),
            taken + jnp.sum(done, dtype=jnp.int32),
            step + 1,
        )

    zero = jnp.zeros(L, jnp.int32)
    lane = jnp.arange(L, dtype=jnp.int32)
    start = (flat, lane, zero, zero + 1, jnp.asarray(L, jnp.int32), jnp.asarray(0, jnp.int32))
    flat = jax.lax.while_loop(cond, body, start)[0]
    source = (jnp.arange(B)[:, None] * G + run_start).reshape(n)
    return flat[source].reshape(B, G, K, W)


def labels_from_membership(membership: Array, mask: Mask) -> Array:
    """``(K,)`` int32 head index of each live component (``-1`` on padded slots)."""
    head = jnp.argmax(membership, axis=0).astype(jnp.int32)
    covered = jnp.any(membership, axis=0)
    return jnp.where(mask & covered, head, -1)


def gauss_cluster(
    gm: GaussianMixture,
    lam: ArrayLike,
    *,
    dims: Sequence[int] | None = None,
    triangular: bool = False,
    subset_rule: str = "split",
    range_scale: ArrayLike = 0.5,
    delta: Array | None = None,
    dist: Array | None = None,
) -> ClusterResult:
    """Distribution-similarity clustering at confidence multiplier ``λ`` (seed 000 eqs 23–28).

    Args:
        gm: mixture with capacity ``K`` (weights are not used).
        lam: ``()`` confidence multiplier, ``σ* = λσ`` (Assumption 1), or ``(G,)`` multipliers (a
            search grid): the ``G`` clusterings are resolved in one loop (:func:`resolve_overlaps`).
        dims: static clustering dimensions (default all).
        triangular: seed 003's upper-triangular judgment matrix (eqs 4, 6) instead of seed 000's
            symmetric one (eqs 24–25).
        subset_rule: Situation 3 handling, ``"split"`` (seed 000) or ``"absorb"`` (seed 003).
        range_scale: ``s``, the confidence scope is ``s·λσ`` (module docstring; default 0.5).
        delta, dist: precomputed :func:`similarity_thresholds` / :func:`centre_distances` (to share
            them across many ``λ``).

    Returns:
        A :class:`ClusterResult`, with a leading ``(G,)`` axis on every field when ``lam`` is
        ``(G,)``; hard clustering is piecewise constant in ``λ`` (it changes only where ``λ``
        crosses some ``δ_ij``).
    """
    dims = None if dims is None else tuple(int(i) for i in dims)
    if delta is None:
        delta = similarity_thresholds(gm, dims)
    if dist is None:
        dist = centre_distances(gm, dims)
    # materialised once: otherwise XLA re-evaluates δ inside the judgment of every grid point
    delta, dist = jax.lax.optimization_barrier((delta, dist))
    lam = jnp.asarray(lam, delta.dtype)
    if lam.ndim > 1:
        raise ValueError(f"lam: expected a scalar or a (G,) grid, got shape {lam.shape}")
    radius = jnp.asarray(range_scale, delta.dtype) * jnp.atleast_1d(lam)
    absorb = _is_absorb(subset_rule)
    r = jax.vmap(lambda rad: judgment_matrix(delta, rad, gm.mask, triangular=triangular))(radius)
    # Packed at once: the sweep, Step 1 and the pair search then touch words, not (K, K) booleans
    # (and XLA does not re-evaluate δ inside each of Step 1's (K, K, K) comparisons).
    packed = jax.vmap(_combine_identical_packed)(_pack(r))
    membership = _unpack(_resolve_packed(packed, dist, absorb), gm.capacity)
    labels = jax.vmap(labels_from_membership, in_axes=(0, None))(membership, gm.mask)
    n_clusters = jnp.sum(jnp.any(membership, axis=-1).astype(jnp.int32), axis=-1)
    result = ClusterResult(labels, membership, n_clusters, r)
    if lam.ndim == 0:
        return ClusterResult(*(a[0] for a in result))
    return result
