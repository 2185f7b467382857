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
   list of ``K(K-1)/2`` pairs; a bounded ``lax.while_loop`` jumps over pairs that share nothing,
   which are no-ops), each time in the *current* state of the clusters:

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

from functools import partial
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import gaussian
from gmjax._types import Array, ArrayLike, Mask
from gmjax.mixture import GaussianMixture

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
    K = membership.shape[0]
    same = jnp.all(membership[:, None, :] == membership[None, :, :], axis=-1)  # (K, K)
    lower = jnp.asarray(np.tril(np.ones((K, K), bool), k=-1))  # j < i
    nonempty = jnp.any(membership, axis=-1)
    dup = jnp.any(same & lower & nonempty[None, :], axis=-1)
    return membership & ~dup[:, None]


def _pair_step(dist: Array, membership: Array, pair: Array, absorb: bool = False) -> Array:
    """Fine-tune one cluster pair ``(i, j)`` (seed 000 eqs 26–28); see the module docstring."""
    i, j = pair[0], pair[1]
    ci, cj = membership[i], membership[j]
    ov = ci & cj
    any_ov = jnp.any(ov)
    j_in_i = jnp.all(cj <= ci)  # C_j ⊆ C_i
    i_in_j = jnp.all(ci <= cj)  # C_i ⊆ C_j
    identical = j_in_i & i_in_j
    # Situation 2: eq 27 renew, eq 28 nearest-member distance, Step 2.3 re-assignment.
    ri, rj = ci & ~ov, cj & ~ov
    inf = jnp.asarray(jnp.inf, dist.dtype)
    di = jnp.min(jnp.where(ri[:, None], dist, inf), axis=0)  # (K,) distance of each m to C_i*
    dj = jnp.min(jnp.where(rj[:, None], dist, inf), axis=0)
    to_i = di <= dj
    s2_i = ri | (ov & to_i)
    s2_j = rj | (ov & ~to_i)
    empty = jnp.zeros_like(ci)
    if absorb:  # Situation 3, seed 003 H2: the superset keeps everything.
        s3_i = jnp.where(j_in_i, ci, empty)
        s3_j = jnp.where(j_in_i, empty, cj)
    else:  # Situation 3, seed 000: the subset survives, the superset keeps its complement.
        s3_i = jnp.where(j_in_i, ci & ~cj, ci)
        s3_j = jnp.where(j_in_i, cj, cj & ~ci)
    sub = j_in_i | i_in_j
    new_i = jnp.where(identical, ci, jnp.where(sub, s3_i, s2_i))
    new_j = jnp.where(identical, empty, jnp.where(sub, s3_j, s2_j))
    new_i = jnp.where(any_ov, new_i, ci)
    new_j = jnp.where(any_ov, new_j, cj)
    return membership.at[i].set(new_i).at[j].set(new_j)


@partial(jax.jit, static_argnames=("subset_rule",))
def resolve_overlaps(membership: Array, dist: Array, *, subset_rule: str = "split") -> Array:
    """Turn overlapping row clusters into a partition (seed 000 eqs 26–28 Steps 2–3).

    Args:
        membership: ``(K, K)`` bool, row ``c`` is cluster ``c``.
        dist: ``(K, K)`` Euclidean centre distances (eq 28).
        subset_rule: ``"split"`` (seed 000 Situation 3) or ``"absorb"`` (seed 003 H2).

    Returns:
        ``(K, K)`` bool with pairwise-disjoint rows covering the same components.
    """
    if subset_rule not in ("split", "absorb"):
        raise ValueError(f"subset_rule: expected 'split' or 'absorb', got {subset_rule!r}")
    absorb = subset_rule == "absorb"
    K = membership.shape[0]
    if K < 2:
        return membership
    idx = jnp.arange(K)
    max_iter = K * (K - 1) // 2 + K  # every pair once plus one row advance per row

    # Visit the pairs (i, j), i < j, in lexicographic order, but jump straight to the next j
    # whose cluster currently shares a component with cluster i: the skipped pairs are
    # Situation 1 (no-ops), so this is the full sweep at a cost proportional to the overlaps.
    def cond(state):
        _, i, _, it = state
        return (i < K - 1) & (it < max_iter)

    def body(state):
        m, i, j, it = state
        shares = jnp.any(m[i][None, :] & m, axis=1) & (idx >= j) & (idx > i)
        found = jnp.any(shares)
        jj = jnp.argmax(shares).astype(i.dtype)
        m_new = _pair_step(dist, m, jnp.stack([i, jj]), absorb)
        m = jax.tree_util.tree_map(lambda a, b: jnp.where(found, a, b), m_new, m)
        i_next = jnp.where(found, i, i + 1)
        j_next = jnp.where(found, jj + 1, i + 2)
        return m, i_next, j_next, it + 1

    zero = jnp.zeros((), jnp.int32)
    out, *_ = jax.lax.while_loop(cond, body, (membership, zero, zero + 1, zero))
    return out


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
        lam: ``()`` confidence multiplier, ``σ* = λσ`` (Assumption 1).
        dims: static clustering dimensions (default all).
        triangular: seed 003's upper-triangular judgment matrix (eqs 4, 6) instead of seed 000's
            symmetric one (eqs 24–25).
        subset_rule: Situation 3 handling, ``"split"`` (seed 000) or ``"absorb"`` (seed 003).
        range_scale: ``s``, the confidence scope is ``s·λσ`` (module docstring; default 0.5).
        delta, dist: precomputed :func:`similarity_thresholds` / :func:`centre_distances` (to share
            them across many ``λ``).

    Returns:
        A :class:`ClusterResult`; hard clustering is piecewise constant in ``λ`` (it changes only
        where ``λ`` crosses some ``δ_ij``).
    """
    dims = None if dims is None else tuple(int(i) for i in dims)
    if delta is None:
        delta = similarity_thresholds(gm, dims)
    if dist is None:
        dist = centre_distances(gm, dims)
    radius = jnp.asarray(range_scale, delta.dtype) * jnp.asarray(lam, delta.dtype)
    r = judgment_matrix(delta, radius, gm.mask, triangular=triangular)
    membership = resolve_overlaps(combine_identical(r), dist, subset_rule=subset_rule)
    labels = labels_from_membership(membership, gm.mask)
    n_clusters = jnp.sum(jnp.any(membership, axis=1).astype(jnp.int32))
    return ClusterResult(labels, membership, n_clusters, r)
