"""Extended ISE (EISE) of a cluster-merge and the search for the confidence multiplier ``λ``.

The EISE of a clustering (Xu et al., PCM = seed 000 eqs 29–35; Xu et al. 2019 = seed 003 eqs 10–15) is the sum over clusters of the
integrated squared error between the cluster's sub-mixture ``f_c = Σ_{m∈c} w_m N(u_m, P_m)`` and its
merged Gaussian ``q_c = W_c N(ū_c, P̄_c)``, plus a penalty on the number of clusters ``N'``:

* seed 000 eq 29: ``J = ½ Σ_c ∫ (f_c - q_c)² + α e^{N'/N}`` (``N`` = components after pruning),
* seed 003 eq 10: ``J = Σ_c ∫ (f_c - q_c)² + α lg N'``.

Each integral is ``J_hh - 2 J_hr + J_rr`` (eq 31) in closed form through
``∫ N(u_1, P_1) N(u_2, P_2) = N(u_1; u_2, P_1 + P_2)`` (eqs 34–35).

**Why a relaxation.** The hard clustering changes only where ``λ`` crosses one of the finitely many
similarity thresholds ``δ_ij`` (see :mod:`gmjax.reduction.clustering`), so the hard EISE is
*piecewise constant* in ``λ``: its derivative is 0 almost everywhere and undefined at the jumps, and
the Newton–Raphson iteration of seed 000 (Table 1 step 7, "the classic Newton–Raphson method") has
nothing to work with. We therefore run Newton on a smooth relaxation with *soft memberships*:

* the hard clusterings ``A_k`` (one-hot ``(K, K)`` membership, clusters indexed by head slot) are
  computed on a grid ``λ_1 < … < λ_G`` over the search scope;
* at any ``λ`` the soft membership is ``A(λ) = Σ_k π_k(λ) A_k`` with temperature weights
  ``π_k(λ) = softmax_k(-(λ - λ_k)² / (2τ²))``; every component is spread over the clusters that
  claim it near ``λ``, each cluster is merged with these fractional weights (the same CI or moment
  formula), and the closed-form EISE is evaluated on the soft clusters, with the soft count
  ``N'(λ) = Σ_k π_k N'_k`` in the penalty;
* as ``τ → 0`` the relaxation tends to the hard EISE of the nearest grid point; for ``τ > 0`` it is
  ``C^∞`` in ``λ``. The Newton step takes its first and second derivative from the chain rule
  through ``π(λ)`` worked out by hand (``_relaxed_value_and_slopes``; equal to ``jax.jvp`` of the value to
  rounding, and cheaper), and ``jax.grad`` differentiates through all of it.

**Cost.** ``A(λ)`` enters the merge statistics linearly and ``J_hh`` bilinearly, so the search
builds the per-grid-point sums once (``_RelaxedParts``: ``Σ ω``, ``Σ ω P^{-1}``, ``Σ ω P^{-1} u``
or the moment sums per cluster, and the ``(G, G)`` matrix of ``J_hh`` cross sums); each relaxed
evaluation then combines them with ``π(λ)`` and needs ``J_hr`` only for the ``G K`` pairs (component,
the cluster a grid point puts it in). Equal to the dense soft merge to rounding
(``tests/test_pcm.py``). Neighbouring grid points mostly cluster alike, so few of those pairs are
distinct; for ``d >= 2`` the search evaluates each distinct pair once (``_Pairs``, ``_over_pairs``;
under ``vmap`` the distinct pairs of all runs side by side): in 4-D, where the pairs' ``d × d``
algebra dominates, a relaxed evaluation costs a little over a quarter of one over all pairs.

Newton starts at the grid's best ``λ`` and takes damped steps (trust radius ``τ``, backtracking; see
:func:`_newton`; every candidate ``λ`` is evaluated with its derivatives, which the next step
starts from, so a step whose full length is accepted costs one evaluation); it fails when a
derivative is not finite or no step decreases the relaxation. The hard EISE at Newton's ``λ`` is
then computed, and the grid's best is kept whenever Newton failed or did not do at least as well
(``used_fallback`` in the result).
The clustering at Newton's ``λ`` is a grid point's wherever the two judgment matrices are equal
(the clustering depends on ``λ`` only through it); only the other runs run the overlap sweep
(:func:`_cluster_unless_known`; under ``vmap`` gathered into blocks).
Newton's loops exit early (under ``vmap`` each pass steps only the runs still stepping, gathered
into chunks, until every run of the batch is done, and only the few runs whose full step was
rejected halve it, gathered into blocks); a custom JVP differentiates the
equivalent fixed-length ``scan``, so values and derivatives are those of ``newton_steps`` masked
steps. For that, a run's relaxed value and slopes must not depend on the batch they are evaluated
in: ``_relaxed_value_and_slopes`` sums elementwise in a fixed order (XLA:CPU gives large reductions
and dots to other kernels that sum in another order), except its three ``π``-weighted grid sums
(``dot``s, which keep their order from 32 runs up; checked in ``tests/test_pcm.py``).
"""

from __future__ import annotations

import functools
from functools import partial
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._types import Array, ArrayLike, DTypeLike
from gmjax.mixture import GaussianMixture
from gmjax.reduction.clustering import (
    centre_distances,
    gauss_cluster,
    judgment_matrix,
    similarity_thresholds,
)

__all__ = [
    "SearchResult",
    "onehot_membership",
    "merge_membership",
    "cluster_ise",
    "self_overlaps",
    "eise",
    "penalty",
    "hard_eise",
    "relaxed_membership",
    "relaxed_eise",
    "search_confidence",
]

_METHODS = ("ci", "moment")
_REGULARIZERS = ("exp", "log10")
_FLAT_EPS = 64  # Newton takes no step whose predicted change |f'| τ is below 64 ε |f|


def _check_options(method: str, regularizer: str) -> None:
    if method not in _METHODS:
        raise ValueError(f"method: expected one of {_METHODS}, got {method!r}")
    if regularizer not in _REGULARIZERS:
        raise ValueError(f"regularizer: expected one of {_REGULARIZERS}, got {regularizer!r}")


def onehot_membership(labels: Array, num_clusters: int, dtype: DTypeLike | None = None) -> Array:
    """``(K, C)`` float membership ``A[m, c] = [labels[m] == c]`` (rows of ``-1`` labels are 0)."""
    dtype = jnp.float32 if dtype is None else dtype
    return (labels[:, None] == jnp.arange(num_clusters)[None, :]).astype(dtype)


_UNROLL_MEMBERS = 32  # member sums unrolled up to this capacity, a fori_loop above it


def _sum_over_members(term, num_members: int):
    """``term(0) + term(1) + … + term(K - 1)``, left to right (``term(m)`` an array, ``m`` a Python
    int where unrolled, else traced)."""
    if num_members <= _UNROLL_MEMBERS:
        return functools.reduce(jnp.add, [term(m) for m in range(num_members)])
    return jax.lax.fori_loop(1, num_members, lambda m, acc: acc + term(m), term(0))


def _cluster_sums(values: Array, labels: Array, num_clusters: int) -> Array:
    """``(C, ...)`` sums of ``values`` ``(K, ...)`` over each hard cluster (``labels == c``; slots
    labelled ``-1`` are left out): the one-hot product ``Aᵀ values`` without the ``(K, C)`` matrix,
    ``O(K)`` additions instead of ``O(K C)`` multiply-adds."""
    ids = jnp.where(labels >= 0, labels, num_clusters)
    return jax.ops.segment_sum(values, ids, num_segments=num_clusters + 1)[:num_clusters]


def merge_membership(
    gm: GaussianMixture, membership: Array, method: str = "ci", *, info: Array | None = None
) -> GaussianMixture:
    """Merge every (soft) cluster into one Gaussian: a mixture of capacity ``C``.

    With fractional weights ``ω_mc = A_mc w_m`` and ``W_c = Σ_m ω_mc``:

    * ``"ci"`` — covariance intersection with normalised weights (seed 000 eqs 38–39, "we utilize
      the normalized weights instead of searching for the optimal weighted coefficients"):
      ``P̄_c^{-1} = Σ_m (ω_mc / W_c) P_m^{-1}``, ``ū_c = P̄_c Σ_m (ω_mc / W_c) P_m^{-1} u_m``;
    * ``"moment"`` — moment preserving (seed 003 eqs 16–18):
      ``ū_c = Σ ω u / W``, ``P̄_c = Σ ω (P + (u - ū)(u - ū)^T) / W``.

    The merged weight is ``W_c`` (seed 000: "the sum of component weights in the cluster"; seed 003
    eq 16), so the total weight is preserved. Empty clusters are padded slots.

    Args:
        gm: mixture of capacity ``K``.
        membership: ``(K, C)`` non-negative, rows of live components summing to 1 (one-hot for a
            hard clustering).
        method: ``"ci"`` or ``"moment"``.
        info: optional ``(K, d, d)`` ``P_m^{-1}`` (``gaussian.spd_inv(gm.covs)``), when the caller
            merges many clusterings of the same mixture (the confidence search).
    """
    if method not in _METHODS:
        raise ValueError(f"method: expected one of {_METHODS}, got {method!r}")
    dtype = gm.means.dtype
    w = jnp.where(gm.mask, gm.weights, 0.0).astype(dtype)
    A = jnp.where(gm.mask[:, None], membership.astype(dtype), 0.0)
    omega = A * w[:, None]  # (K, C)
    W = jnp.sum(omega, axis=0)  # (C,)
    live = W > 0
    W_safe = jnp.where(live, W, 1.0)
    frac = omega / W_safe[None, :]  # (K, C), columns sum to 1 on live clusters
    d = gm.dim
    eye = jnp.eye(d, dtype=dtype)
    if method == "moment":
        mu = frac.T @ gm.means  # (C, d)
        dev = gm.means[None, :, :] - mu[:, None, :]  # (C, K, d)
        spread = jnp.einsum("kc,cki,ckj->cij", frac, dev, dev)
        within = jnp.einsum("kc,kij->cij", frac, gm.covs)
        cov = gaussian.symmetrize(within + spread)
    else:
        info = gaussian.spd_inv(gm.covs) if info is None else info  # (K, d, d); padded slots hold I
        info = jnp.where(gm.mask[:, None, None], info, 0.0)
        info_c = jnp.einsum("kc,kij->cij", frac, info)
        info_c = jnp.where(live[:, None, None], info_c, eye)
        cov = gaussian.spd_inv(info_c)
        eta = jnp.einsum("kc,kij,kj->ci", frac, info, gm.means)
        mu = jnp.einsum("cij,cj->ci", cov, eta)
    mu = jnp.where(live[:, None], mu, 0.0)
    cov = jnp.where(live[:, None, None], cov, eye)
    return GaussianMixture(jnp.where(live, W, 0.0), mu, cov, live)


def _pair_log_overlaps(ma: Array, Pa: Array, mb: Array, Pb: Array) -> Array:
    """``(A, B)`` ``log ∫ N(ma, Pa) N(mb, Pb) = log N(ma; mb, Pa + Pb)`` (seed 000 eqs 34–35)."""
    return gaussian.spd_logpdf(ma[:, None, :], mb[None, :, :], Pa[:, None] + Pb[None, :])


def self_overlaps(gm: GaussianMixture) -> Array:
    """``(K, K)`` ``∫ N(u_m, P_m) N(u_n, P_n)`` between the live components (0 where either is padded)."""
    live = gm.mask[:, None] & gm.mask[None, :]
    return jnp.exp(jnp.where(live, _pair_log_overlaps(gm.means, gm.covs, gm.means, gm.covs), -jnp.inf))


def cluster_ise(
    gm: GaussianMixture,
    membership: Array,
    merged: GaussianMixture,
    *,
    overlaps: Array | None = None,
    labels: Array | None = None,
) -> Array:
    """``(C,)`` per-cluster ``∫ (f_c - q_c)² = J_hh - 2 J_hr + J_rr`` (seed 000 eqs 31, 35).

    ``f_c = Σ_m A_mc w_m N(u_m, P_m)`` and ``q_c`` is slot ``c`` of ``merged``.

    Args:
        gm, membership, merged: the mixture ``(K)``, the ``(K, C)`` membership and the merged clusters.
        overlaps: optional :func:`self_overlaps` of ``gm`` (independent of the clustering: the
            confidence search computes it once for all its grid points).
        labels: for a hard clustering, ``membership``'s ``(K,)`` labels (cluster of each slot, ``-1``
            for none): ``J_hr`` then needs each component against its own cluster only (``K``
            evaluations instead of ``K C``; the same sum).
    """
    dtype = gm.means.dtype
    w = jnp.where(gm.mask, gm.weights, 0.0).astype(dtype)
    Aw = jnp.where(gm.mask[:, None], membership.astype(dtype), 0.0) * w[:, None]  # (K, C)
    S = self_overlaps(gm) if overlaps is None else overlaps
    if labels is None:
        S_cross = jnp.exp(
            jnp.where(
                gm.mask[:, None] & merged.mask[None, :],
                _pair_log_overlaps(gm.means, gm.covs, merged.means, merged.covs),
                -jnp.inf,
            )
        )
        cross = jnp.einsum("mc,mc->c", Aw, S_cross)
    else:
        own = jnp.maximum(labels, 0)
        live = gm.mask & (labels >= 0) & merged.mask[own]
        log_own = gaussian.spd_logpdf(gm.means, merged.means[own], gm.covs + merged.covs[own])
        cross = jnp.einsum("mc,m->c", Aw, jnp.exp(jnp.where(live, log_own, -jnp.inf)))
    self_norm = jnp.exp(gaussian.spd_logpdf(merged.means, merged.means, 2.0 * merged.covs))
    Wc = jnp.where(merged.mask, merged.weights, 0.0)
    if labels is None:
        j_hh = jnp.einsum("mc,mn,nc->c", Aw, S, Aw)
    else:  # Σ_{m, n ∈ c} w_m w_n S_mn: O(K²) instead of the one-hot O(K² C)
        lab = jnp.where(gm.mask, labels, -1)
        same = (lab[:, None] == lab[None, :]) & (lab[:, None] >= 0)
        row = jnp.where(same, S, 0.0) @ w  # a dot: the same rounding wherever it is compiled
        j_hh = _cluster_sums(w * row, lab, Aw.shape[1])
    j_hr = cross * Wc
    j_rr = Wc * Wc * self_norm
    return jnp.where(merged.mask, j_hh - 2.0 * j_hr + j_rr, 0.0)


def penalty(n_clusters: ArrayLike, n_ref: ArrayLike, alpha: ArrayLike, regularizer: str = "exp") -> Array:
    """``α e^{N'/N}`` (seed 000 eq 29) or ``α lg N'`` (seed 003 eq 10)."""
    n_clusters = jnp.asarray(n_clusters)
    if regularizer == "exp":
        n_ref = jnp.asarray(n_ref, n_clusters.dtype)
        ratio = n_clusters / jnp.where(n_ref > 0, n_ref, 1)
        return alpha * jnp.exp(ratio)
    if regularizer == "log10":
        safe = jnp.where(n_clusters > 0, n_clusters, 1)
        return alpha * jnp.log10(safe)
    raise ValueError(f"regularizer: expected one of {_REGULARIZERS}, got {regularizer!r}")


def eise(
    gm: GaussianMixture,
    membership: Array,
    merged: GaussianMixture,
    n_clusters: ArrayLike,
    n_ref: ArrayLike,
    *,
    alpha: ArrayLike,
    regularizer: str = "exp",
    ise_scale: float = 0.5,
    clip: bool = True,
    overlaps: Array | None = None,
    labels: Array | None = None,
) -> Array:
    """The EISE ``ise_scale · Σ_c ∫ (f_c - q_c)² + penalty(N')`` (seed 000 eq 29 / seed 003 eq 10).

    Args:
        gm, membership, merged: as in :func:`cluster_ise`.
        n_clusters: ``N'`` (may be fractional for the relaxation).
        n_ref: ``N``, the number of components entering the clustering (seed 000's ``e^{N'/N}``).
        alpha: regularisation constant (seed 000 §IV: 0.001; seed 003 §4.2: 0.3).
        regularizer: ``"exp"`` (seed 000) or ``"log10"`` (seed 003).
        ise_scale: ``0.5`` for seed 000 eq 29, ``1.0`` for seed 003 eq 10.
        clip: clip each cluster's integral at 0 (rounding can make a singleton's ``0`` negative).
        overlaps, labels: see :func:`cluster_ise`.
    """
    per = cluster_ise(gm, membership, merged, overlaps=overlaps, labels=labels)
    if clip:
        per = jnp.maximum(per, 0.0)
    return ise_scale * jnp.sum(per) + penalty(n_clusters, n_ref, alpha, regularizer)


@partial(jax.jit, static_argnames=("method", "regularizer", "ise_scale"))
def hard_eise(
    gm: GaussianMixture,
    labels: Array,
    *,
    alpha: ArrayLike,
    method: str = "ci",
    regularizer: str = "exp",
    ise_scale: float = 0.5,
    overlaps: Array | None = None,
    info: Array | None = None,
) -> tuple[Array, GaussianMixture, Array]:
    """Merge a hard clustering (labels = head slot, ``-1`` for padding) and its EISE.

    ``overlaps`` (:func:`self_overlaps`) and ``info`` (``P_m^{-1}``) are optional precomputations
    of the clustering-independent parts (see :func:`cluster_ise`, :func:`merge_membership`).

    Returns:
        ``(eise, merged, n_clusters)`` with ``merged`` of capacity ``K`` indexed by head slot.
    """
    _check_options(method, regularizer)
    K = gm.capacity
    A = onehot_membership(labels, K, gm.means.dtype)
    merged = merge_membership(gm, A, method, info=info)
    n_clusters = jnp.sum(merged.mask.astype(jnp.int32))
    n_ref = jnp.sum(gm.mask.astype(jnp.int32))
    value = eise(
        gm,
        A,
        merged,
        n_clusters.astype(gm.means.dtype),
        n_ref,
        alpha=alpha,
        regularizer=regularizer,
        ise_scale=ise_scale,
        overlaps=overlaps,
        labels=labels,
    )
    return value, merged, n_clusters


def relaxed_membership(
    lam: ArrayLike, grid: Array, grid_labels: Array, temperature: ArrayLike
) -> tuple[Array, Array]:
    """Soft memberships ``A(λ) = Σ_k π_k(λ) A_k`` and the weights ``π(λ)``.

    Args:
        lam: ``()`` confidence multiplier.
        grid: ``(G,)`` grid of ``λ``.
        grid_labels: ``(G, K)`` hard labels at the grid points.
        temperature: ``τ > 0``, in units of ``λ``.
    """
    K = grid_labels.shape[1]
    dtype = grid.dtype
    logits = -0.5 * ((lam - grid) / temperature) ** 2
    pi = jax.nn.softmax(logits)
    A_k = jax.vmap(lambda lab: onehot_membership(lab, K, dtype))(grid_labels)  # (G, K, K)
    return jnp.einsum("g,gkc->kc", pi, A_k), pi


class _RelaxedParts(NamedTuple):
    """The ``λ``-independent parts of one mixture's relaxed EISE over one grid (built once per search).

    Every quantity the relaxation needs is linear (merge statistics) or bilinear (``J_hh``) in the
    soft membership ``A(λ) = Σ_k π_k(λ) A_k``, so it is a ``π``-weighted sum of per-grid-point sums:

    * ``weights`` ``(G, C)``: ``Σ_m [A_k]_mc w_m``;
    * ``first`` ``(G, C, d)`` and ``second`` ``(G, C, d, d)``: for ``"ci"`` ``Σ ω P_m^{-1} u_m`` and
      ``Σ ω P_m^{-1}``; for ``"moment"`` ``Σ ω (u_m - s_c)`` and ``Σ ω (P_m + (u_m - s_c)(u_m - s_c)^T)``
      about the head's mean ``s_c`` (``shift``), which keeps the spread free of cancellation;
    * ``hh`` ``(G, G)``: ``Σ_c (A_k w)_c^T S (A_l w)_c``, so ``Σ_c J_hh,c(λ) = π^T hh π``;
    * ``pairs``: ``J_hr``'s distinct (component, cluster) pairs (:class:`_Pairs`), or ``None`` for
      ``d = 1``.
    """

    gm: GaussianMixture
    grid: Array
    labels: Array
    counts: Array
    weights: Array
    first: Array
    second: Array
    shift: Array
    hh: Array
    pairs: _Pairs | None


class _Pairs(NamedTuple):
    """``J_hr``'s ``G K`` terms ``(g, m)`` pair component ``m`` with the cluster ``l_g(m)`` grid point
    ``g`` puts it in, and the pair's term does not depend on ``g``; neighbouring grid points mostly
    cluster alike, so few pairs are distinct (on the seed 000 4-D system about 7 of 220 on average,
    at most 81 in 10 × 1000). :func:`_over_pairs` evaluates each distinct pair once.

    Attributes:
        member, cluster: ``(n,)`` int32 (``n >= G K``, a whole number of :func:`_pair_chunk`), the
            distinct pairs ``(m, c)`` first (by ``m``, then by the first grid point that makes
            them), then ``(0, 0)``.
        of: ``(G, K)`` int32, the index of pair ``(g, m)`` in ``member`` / ``cluster`` (0 on padding).
        n_distinct: ``()`` int32, the number of distinct pairs.
    """

    member: Array
    cluster: Array
    of: Array
    n_distinct: Array


def _pair_chunk(n_pairs: int, runs: int = 1) -> int:
    """How many pairs :func:`_over_pairs` evaluates at a time: alone, a quarter of a run's
    ``n_pairs = G K``; under ``vmap`` over ``runs`` runs, a sixteenth of all runs' ``n_pairs``
    (the batch's distinct pairs side by side: on the seed 000 4-D system about 3 % of them)."""
    return -(-n_pairs * runs // (4 if runs == 1 else 16))


def _distinct_pairs(labels: Array) -> _Pairs:
    """:class:`_Pairs` of the hard clusterings ``labels`` ``(G, K)`` (``-1`` on padding)."""
    G, K = labels.shape
    chunk = _pair_chunk(G * K)
    size = -(-G * K // chunk) * chunk
    live = labels >= 0
    same = labels[:, None, :] == labels[None, :, :]  # (G, G, K): l_g(m) == l_h(m)
    first = jnp.argmax(same, axis=1)  # (G, K): the first grid point that makes pair (g, m)
    new = live & (first == jnp.arange(G)[:, None])
    number = (jnp.cumsum(new.T.ravel()) - 1).astype(jnp.int32).reshape(K, G).T  # by m, then g
    of = jnp.where(live, jnp.take_along_axis(number, first, axis=0), 0)
    slot = jnp.where(new, number, size)  # out of range: dropped
    members = jnp.broadcast_to(jnp.arange(K, dtype=jnp.int32), (G, K))
    member = jnp.zeros(size, jnp.int32).at[slot].set(members, mode="drop")
    cluster = jnp.zeros(size, jnp.int32).at[slot].set(labels.astype(jnp.int32), mode="drop")
    count = jax.lax.stop_gradient(jnp.sum(new.astype(jnp.int32)))
    return _Pairs(member, cluster, of, count)


def _over_pairs(fn, parts: _RelaxedParts, at_cluster) -> tuple[Array, ...]:
    """``fn(u, P, s)``'s arrays at ``J_hr``'s ``(G, K)`` pairs: component ``(u_m, P_m)`` and ``s``,
    the pytree ``at_cluster`` of per-cluster arrays ``(C, ...)`` at the cluster ``c = l_g(m)``
    (``fn`` elementwise in the pairs, over any leading shape).

    For ``d = 1`` over all ``G K`` pairs at once; otherwise once per distinct pair (:class:`_Pairs`),
    then gathered. Alone, a chunk of :func:`_pair_chunk` pairs at a time for as many chunks as the
    run needs. Under ``vmap`` the distinct pairs of all the batch's runs side by side, in chunks of a
    sixteenth of all runs' pairs (usually one), so that no run evaluates pairs it does not have.
    The same arithmetic on the same inputs, so equal to rounding (XLA may fuse the programs
    differently: a few ulps in ``tests/test_pcm.py``'s 2-D cases; on 5 × 1000 captured 4-D
    benchmark searches every result bit-identical). The loops have no reverse mode.
    """
    gm = parts.gm
    if parts.pairs is None:
        at_own = jax.tree_util.tree_map(lambda a: a[jnp.maximum(parts.labels, 0)], at_cluster)
        return fn(gm.means[None], gm.covs[None], at_own)

    def alone(member, cluster, of, count, means, covs, at_cluster):
        chunk = _pair_chunk(of.size)

        def at_chunk(j):
            m = jax.lax.dynamic_slice_in_dim(member, j * chunk, chunk)
            c = jax.lax.dynamic_slice_in_dim(cluster, j * chunk, chunk)
            return fn(means[m], covs[m], jax.tree_util.tree_map(lambda a: a[c], at_cluster))

        def next_chunk(state):
            j, buffers = state
            values = at_chunk(j)
            return j + 1, tuple(
                jax.lax.dynamic_update_slice_in_dim(b, v, j * chunk, 0) for b, v in zip(buffers, values)
            )

        buffers = tuple(jnp.zeros(member.shape + s.shape[1:], s.dtype) for s in jax.eval_shape(at_chunk, 0))
        _, buffers = jax.lax.while_loop(lambda s: s[0] * chunk < count, next_chunk, (0, buffers))
        return tuple(b[of] for b in buffers)

    side_by_side = jax.custom_batching.custom_vmap(alone)

    @side_by_side.def_vmap
    def _batch_rule(axis_size, in_batched, *operands):
        spread = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + jnp.shape(a))  # noqa: E731
        member, cluster, of, count, means, covs, at_cluster = (
            jax.tree_util.tree_map(spread, a, b) for a, b in zip(operands, in_batched)
        )
        B, size = member.shape
        chunk = _pair_chunk(of.shape[1] * of.shape[2], B)
        ends = jnp.cumsum(count)  # the batch's distinct pairs, run after run
        total = ends[-1] if B else jnp.zeros((), count.dtype)

        def at_chunk(j):  # the batch's pairs j chunk, …, (j + 1) chunk - 1: run r, its pair k
            flat = j * chunk + jnp.arange(chunk, dtype=count.dtype)
            r = jnp.minimum(jnp.searchsorted(ends, flat, side="right"), B - 1)
            k = jnp.clip(flat - (ends[r] - count[r]), 0, size - 1)
            m, c = member[r, k], cluster[r, k]
            s = jax.tree_util.tree_map(lambda a: a[r, c], at_cluster)
            return fn(means[r, m], covs[r, m], s), jnp.where(flat < total, r, B), k  # r = B: dropped

        def next_chunk(state):
            j, buffers = state
            values, r, k = at_chunk(j)
            return j + 1, tuple(b.at[r, k].set(v, mode="drop") for b, v in zip(buffers, values))

        shapes = jax.eval_shape(at_chunk, 0)[0]
        buffers = tuple(jnp.zeros((B, size) + s.shape[1:], s.dtype) for s in shapes)
        _, buffers = jax.lax.while_loop(lambda s: s[0] * chunk < total, next_chunk, (0, buffers))
        out = tuple(jax.vmap(lambda b, o: b[o])(b, of) for b in buffers)
        return out, tuple(True for _ in out)

    pairs = parts.pairs
    return side_by_side(
        pairs.member, pairs.cluster, pairs.of, pairs.n_distinct, gm.means, gm.covs, at_cluster
    )


def _relaxed_parts(
    gm: GaussianMixture,
    grid: Array,
    grid_labels: Array,
    grid_counts: Array,
    method: str,
    *,
    overlaps: Array | None = None,
    info: Array | None = None,
    distinct_pairs: bool = False,
) -> _RelaxedParts:
    """The per-grid-point sums of ``gm``'s hard clusterings ``grid_labels`` ``(G, K)`` at ``grid``
    ``(G,)`` with ``N'`` ``grid_counts`` ``(G,)``; ``overlaps`` and ``info`` as in :func:`hard_eise`.
    ``distinct_pairs``: find ``J_hr``'s distinct pairs (:class:`_Pairs`; for ``d >= 2``: in 1-D the
    gathers cost what they save). The evaluations then loop over them, which has no reverse mode.

    The merge statistics are sums over the members of each cluster (:func:`_cluster_sums`), and
    ``hh[g, h] = Σ_n w_n U_g[l_h(n), n]`` with ``U_g[c, n] = Σ_{m ∈ c} w_m S_mn`` (``l_g(m)`` the
    cluster grid point ``g`` puts ``m`` in), its ``(G, G, K)`` terms ``U_g[l_h(n), n]`` summed
    member by member in slot order: ``O(G² K²)`` selections and additions instead of a one-hot
    product's ``O(G K² C)`` multiply-adds, and no scatter-add into ``U`` (under ``vmap`` on CPU
    that cost several times as much: 24 of 34 µs per mixture, K = 20, 1000 mixtures). Equal to the
    one-hot sums to rounding.
    """
    dtype = gm.means.dtype
    K = gm.capacity
    w = jnp.where(gm.mask, gm.weights, 0.0).astype(dtype)
    labels = jnp.where(gm.mask[None, :], grid_labels, -1)  # (G, K)
    sums = jax.vmap(partial(_cluster_sums, num_clusters=K), in_axes=(None, 0))
    S = self_overlaps(gm) if overlaps is None else overlaps
    own = jnp.maximum(labels, 0)
    wS = w[:, None] * S

    def U_own_term(m):  # member m's part of U[g, l_h(n), n], U[g, c, n] = Σ_{m: l_g(m) = c} w_m S_mn
        return jnp.where(labels[:, None, m, None] == own[None], wS[m][None, None], 0.0)

    U_own = _sum_over_members(U_own_term, K)  # (G, G, K): U[g, l_h(n), n], member by member
    hh = jnp.einsum("ghn,n->gh", jnp.where(labels[None, :, :] >= 0, U_own, 0.0), w)
    if method == "ci":
        info = gaussian.spd_inv(gm.covs) if info is None else info
        w_info = jnp.where(gm.mask[:, None, None], info, 0.0) * w[:, None, None]
        shift = jnp.zeros_like(gm.means)
        first = sums(jnp.einsum("mij,mj->mi", w_info, gm.means), labels)
        second = sums(w_info, labels)
    else:
        shift = jnp.where(gm.mask[:, None], gm.means, 0.0)  # cluster c's head is slot c
        dev = gm.means[None, :, :] - shift[own]  # (G, K, d): u_m - s_c, c = the cluster of m
        wdev = w[None, :, None] * dev
        per_grid_point = jax.vmap(partial(_cluster_sums, num_clusters=K))
        first = per_grid_point(wdev, labels)
        spread = w[None, :, None, None] * gm.covs[None] + wdev[:, :, :, None] * dev[:, :, None, :]
        second = per_grid_point(spread, labels)
    pairs = _distinct_pairs(labels) if distinct_pairs and gm.dim > 1 else None
    return _RelaxedParts(
        gm, grid, grid_labels, grid_counts.astype(dtype), sums(w, labels), first, second, shift, hh, pairs
    )


def _relaxed_value(
    parts: _RelaxedParts,
    lam: ArrayLike,
    *,
    temperature: ArrayLike,
    alpha: ArrayLike,
    method: str,
    regularizer: str,
    ise_scale: float,
) -> Array:
    """The relaxed EISE at ``λ`` from its parts: ``O(G K d²)`` merges and ``G K`` cross terms."""
    gm = parts.gm
    dtype = gm.means.dtype
    d = gm.dim
    eye = jnp.eye(d, dtype=dtype)
    pi = jax.nn.softmax(-0.5 * ((lam - parts.grid) / temperature) ** 2)  # (G,)
    W = pi @ parts.weights  # (C,)
    live = W > 0
    W_safe = jnp.where(live, W, 1.0)
    first = jnp.einsum("g,gci->ci", pi, parts.first) / W_safe[:, None]
    second = jnp.einsum("g,gcij->cij", pi, parts.second) / W_safe[:, None, None]
    if method == "ci":  # seed 000 eqs 38-39 with normalised weights
        cov = gaussian.spd_inv(jnp.where(live[:, None, None], second, eye))
        mu = jnp.einsum("cij,cj->ci", cov, first)
    else:  # seed 003 eqs 16-18, about the head's mean
        mu = parts.shift + first
        cov = gaussian.symmetrize(second - first[:, :, None] * first[:, None, :])
    mu = jnp.where(live[:, None], mu, 0.0)
    cov = jnp.where(live[:, None, None], cov, eye)
    # J_hr: component m against the cluster that grid point k puts it in, weighted by π_k (eq 35)
    own = jnp.maximum(parts.labels, 0)  # (G, K)
    valid = (parts.labels >= 0) & gm.mask[None, :] & live[own]
    (log_cross,) = _over_pairs(lambda u, P, s: (gaussian.spd_logpdf(u, s[0], P + s[1]),), parts, (mu, cov))
    w = jnp.where(gm.mask, gm.weights, 0.0).astype(dtype)
    cross = jnp.exp(jnp.where(valid, log_cross, -jnp.inf)) * W[own] * w[None, :]
    j_hr = pi @ jnp.sum(cross, axis=1)
    j_rr = jnp.sum(jnp.where(live, W * W * jnp.exp(gaussian.spd_logpdf(mu, mu, 2.0 * cov)), 0.0))
    j_hh = pi @ parts.hh @ pi
    n_soft = pi @ parts.counts
    n_ref = jnp.sum(gm.mask.astype(jnp.int32))
    return ise_scale * (j_hh - 2.0 * j_hr + j_rr) + penalty(n_soft, n_ref, alpha, regularizer)


def _relaxed_at(lam, args, *, method: str, regularizer: str, ise_scale: float) -> Array:
    """:func:`_relaxed_value` with its traced arguments ``args = (parts, temperature, alpha)``."""
    parts, temperature, alpha = args
    return _relaxed_value(
        parts,
        lam,
        temperature=temperature,
        alpha=alpha,
        method=method,
        regularizer=regularizer,
        ise_scale=ise_scale,
    )


# Small-matrix products over leading batch axes, unrolled over d (<= 6) into elementwise operations:
# XLA's CPU dot_general on batches of tiny matrices calls a kernel per matrix (as gaussian.py notes).
def _mm(a: Array, b: Array) -> Array:
    """``a @ b`` for ``(..., d, d)`` matrices."""
    if a.shape[-1] > gaussian._UNROLL_MAX_DIM:
        return a @ b
    return functools.reduce(jnp.add, [a[..., :, k, None] * b[..., None, k, :] for k in range(a.shape[-1])])


def _mv(a: Array, x: Array) -> Array:
    """``a @ x`` for ``(..., d, d)`` matrices and ``(..., d)`` vectors."""
    if a.shape[-1] > gaussian._UNROLL_MAX_DIM:
        return jnp.einsum("...ij,...j->...i", a, x)
    return functools.reduce(jnp.add, [a[..., :, k] * x[..., k, None] for k in range(a.shape[-1])])


def _dot(x: Array, y: Array) -> Array:
    """``xᵀ y`` over the last axis."""
    return functools.reduce(jnp.add, [x[..., k] * y[..., k] for k in range(x.shape[-1])])


def _trace_of_product(a: Array, b: Array) -> Array:
    """``tr(a b)`` for ``(..., d, d)`` matrices."""
    return functools.reduce(jnp.add, [_dot(a[..., i, :], b[..., :, i]) for i in range(a.shape[-1])])


# Newton's evaluations of the relaxation run on a whole vmap batch, and its halvings on blocks of the
# runs that need them (_halvings); XLA:CPU hands reductions and dots above some size to other kernels
# (YNNPACK, Eigen), which sum in another order, so a run's value would depend on the batch it is
# evaluated in. The evaluation therefore sums elementwise, left to right (unrolled at trace time),
# except the three π-weighted grid sums, whose dots keep one order from 32 runs up (tests/test_pcm.py)
# and are faster than unrolled sums.
def _sum_last(x: Array) -> Array:
    """``Σ_i x[..., i]``, left to right."""
    return functools.reduce(jnp.add, [x[..., i] for i in range(x.shape[-1])])


def _softmax(logits: Array) -> Array:
    """:func:`jax.nn.softmax` over the last axis with its max and sum unrolled."""
    top = functools.reduce(jnp.maximum, [logits[..., i] for i in range(logits.shape[-1])])
    unnormalized = jnp.exp(logits - top[..., None])
    return unnormalized / _sum_last(unnormalized)[..., None]


def _spd_inv(P: Array) -> Array:
    """:func:`gaussian.spd_inv` with ``L^{-T} L^{-1}`` unrolled for ``3 <= d <= 6``."""
    d = P.shape[-1]
    if d <= 2 or d > gaussian._UNROLL_MAX_DIM:
        return gaussian.spd_inv(P)
    lower_inv = gaussian._lower_inverse(gaussian._cholesky(P))
    return _mm(jnp.swapaxes(lower_inv, -1, -2), lower_inv)


def _spd_logpdf(x: Array, m: Array, P: Array) -> Array:
    """:func:`gaussian.spd_logpdf` with the log-determinant's sum unrolled for ``3 <= d <= 6``."""
    d = P.shape[-1]
    if d <= 2 or d > gaussian._UNROLL_MAX_DIM:
        return gaussian.spd_logpdf(x, m, P)
    L = gaussian._cholesky(P)
    logdet = 2.0 * functools.reduce(jnp.add, [jnp.log(L[..., i, i]) for i in range(d)])
    return -0.5 * (d * gaussian._LOG_2PI + logdet + gaussian.spd_inv_quad(x - m, P))


def _softmax_slopes(pi: Array, a: Array) -> tuple[Array, Array]:
    """``π'`` and ``π''`` of ``π = softmax(l)`` ``(G,)`` with ``l' = a`` and ``l''`` the same for every
    entry (the Gaussian kernel's ``-1/τ²``): ``π' = π (a - ā)``, ``π'' = π ((a - ā)² - Var_π a)``."""
    centred = a - _dot(pi, a)
    return pi * centred, pi * (centred**2 - _dot(pi, centred**2))


def _quotient_slopes(num: Array, den: Array) -> Array:
    """``(3, ...)`` value, first and second derivative of ``num / den`` from those of ``num``
    ``(3, C, ...)`` and of ``den`` ``(3, C)`` (``den[0] > 0``)."""
    den = den.reshape(den.shape + (1,) * (num.ndim - den.ndim))
    q0 = num[0] / den[0]
    q1 = (num[1] - q0 * den[1]) / den[0]
    q2 = (num[2] - 2.0 * q1 * den[1] - q0 * den[2]) / den[0]
    return jnp.stack([q0, q1, q2])


def _penalty_slopes(n: Array, n_ref: Array, alpha: ArrayLike, regularizer: str) -> tuple[Array, Array]:
    """First and second derivative of :func:`penalty` along a path with soft counts ``n`` ``(3,)``
    (value, first and second derivative)."""
    if regularizer == "exp":
        scale = 1.0 / jnp.where(n_ref > 0, n_ref, 1).astype(n.dtype)
        p = alpha * jnp.exp(n[0] * scale)
        return p * n[1] * scale, p * ((n[1] * scale) ** 2 + n[2] * scale)
    positive = n[0] > 0  # penalty() holds lg N' constant (at lg 1) otherwise
    safe = jnp.where(positive, n[0], 1.0)
    r1, r2 = n[1] / safe, n[2] / safe
    return (
        jnp.where(positive, alpha * r1 / jnp.log(10.0), 0.0),
        jnp.where(positive, alpha * (r2 - r1**2) / jnp.log(10.0), 0.0),
    )


def _relaxed_value_and_slopes(
    lam, args, *, method: str, regularizer: str, ise_scale: float
) -> tuple[Array, Array, Array]:
    """Value, first and second derivative in ``λ`` of :func:`_relaxed_at`, derived by hand.

    Forward-over-forward ``jax.jvp`` of the relaxation carries every intermediate through two
    tangent orders; the chain rule through ``π(λ)`` (:func:`_softmax_slopes`) needs only the
    derivatives of the merged clusters ``(W_c, ū_c, P̄_c)`` and, per pair ``(m, c)`` of ``J_hr``
    with ``S = P_m + P̄_c``, ``r = u_m - ū_c``, ``v = S^{-1} r`` and ``ℓ = log N(r; 0, S)``:

    * ``ℓ' = -½ tr(S^{-1} S') + vᵀū' + ½ vᵀ S' v``,
    * ``ℓ'' = -½ tr(S^{-1} S'') + ½ tr(S^{-1} S' S^{-1} S') - zᵀ S^{-1} z + vᵀ ū'' + ½ vᵀ S'' v``
      with ``z = S' v + ū'``,

    and the same with ``S = 2 P̄_c``, ``r = 0`` for ``J_rr``. The value comes with them at little
    cost (the merged clusters and ``ℓ`` are the value's own). Equal to :func:`_relaxed_at` and its
    ``jvp`` derivatives to rounding (``tests/test_pcm.py``); Newton's step uses these.
    """
    parts, temperature, alpha = args
    gm = parts.gm
    dtype = gm.means.dtype
    eye = jnp.eye(gm.dim, dtype=dtype)
    t = (lam - parts.grid) / temperature
    pi = _softmax(-0.5 * t**2)
    pis = jnp.stack([pi, *_softmax_slopes(pi, -t / temperature)])  # (3, G): π, π', π''
    W = pis @ parts.weights  # (3, C)
    live = W[0] > 0
    W = W.at[0].set(jnp.where(live, W[0], 1.0))
    first = _quotient_slopes(jnp.einsum("ng,gci->nci", pis, parts.first), W)  # (3, C, d)
    second = _quotient_slopes(jnp.einsum("ng,gcij->ncij", pis, parts.second), W)  # (3, C, d, d)
    if method == "ci":  # P̄ = Q^{-1}: P̄' = -P̄ Q' P̄, P̄'' = -P̄ Q'' P̄ - 2 P̄' Q' P̄; ū = P̄ F
        prec = jnp.where(live[:, None, None], second[0], eye)
        cov = _spd_inv(prec)
        cov1 = -_mm(cov, _mm(second[1], cov))
        cov2 = -_mm(cov, _mm(second[2], cov)) - 2.0 * _mm(cov1, _mm(second[1], cov))
        mu = jnp.stack(
            [
                _mv(cov, first[0]),
                _mv(cov1, first[0]) + _mv(cov, first[1]),
                _mv(cov2, first[0]) + 2.0 * _mv(cov1, first[1]) + _mv(cov, first[2]),
            ]
        )
    else:  # ū = s + F, P̄ = Q - F Fᵀ
        outer = lambda a, b: a[:, :, None] * b[:, None, :]  # noqa: E731
        mu = first.at[0].add(parts.shift)
        cov = gaussian.symmetrize(second[0] - outer(first[0], first[0]))
        cov1 = second[1] - outer(first[1], first[0]) - outer(first[0], first[1])
        cov2 = (
            second[2]
            - outer(first[2], first[0])
            - 2.0 * outer(first[1], first[1])
            - outer(first[0], first[2])
        )
        cov = jnp.where(live[:, None, None], cov, eye)
        prec = _spd_inv(cov)
    mu = jnp.where(live[None, :, None], mu, 0.0)
    cov1 = jnp.where(live[:, None, None], cov1, 0.0)
    cov2 = jnp.where(live[:, None, None], cov2, 0.0)
    covs = jnp.stack([jnp.where(live[:, None, None], cov, eye), cov1, cov2])  # (3, C, d, d)
    W = jnp.where(live, W, 0.0)

    # J_rr = Σ_c W_c² N(0; 0, 2 P̄_c): ρ = log N, ρ' = -½ tr(P̄^{-1} P̄'), ρ'' as ℓ'' (S = 2 P̄, r = 0)
    e_rr = jnp.exp(_spd_logpdf(mu[0], mu[0], 2.0 * covs[0]))
    pc1 = _mm(prec, covs[1])
    rho1 = -0.5 * _trace_of_product(prec, covs[1])
    rho2 = -0.5 * _trace_of_product(prec, covs[2]) + 0.5 * _trace_of_product(pc1, pc1)
    W0, W1, W2 = W
    j_rr = _sum_last(e_rr * W0**2)
    j_rr1 = _sum_last(e_rr * (2.0 * W0 * W1 + W0**2 * rho1))
    j_rr2 = _sum_last(e_rr * (2.0 * W1**2 + 2.0 * W0 * W2 + 4.0 * W0 * W1 * rho1 + W0**2 * (rho1**2 + rho2)))

    # J_hr = Σ_k π_k Σ_m w_m W_c N(u_m; ū_c, P_m + P̄_c), c = the cluster grid point k puts m in
    own = jnp.maximum(parts.labels, 0)  # (G, K)
    valid = (parts.labels >= 0) & gm.mask[None, :] & live[own]

    def pair_terms(u, P, s):  # ℓ, ℓ', ℓ'' of component (u, P) against cluster s = (ū, P̄ and slopes)
        (m0, m1, m2), (S0, S1, S2) = s
        S = P + S0
        Si = _spd_inv(S)
        v = _mv(Si, u - m0)
        Si_S1 = _mm(Si, S1)
        S1_v = _mv(S1, v)
        z = S1_v + m1
        ell1 = -0.5 * _trace_of_product(Si, S1) + _dot(v, m1) + 0.5 * _dot(v, S1_v)
        ell2 = (
            -0.5 * _trace_of_product(Si, S2)
            + 0.5 * _trace_of_product(Si_S1, Si_S1)
            - _dot(z, _mv(Si, z))
            + _dot(v, m2)
            + 0.5 * _dot(v, _mv(S2, v))
        )
        return _spd_logpdf(u, m0, S), ell1, ell2

    log_cross, ell1, ell2 = _over_pairs(pair_terms, parts, (tuple(mu), tuple(covs)))  # (G, K) each
    w = jnp.where(gm.mask, gm.weights, 0.0).astype(dtype)
    e = jnp.exp(jnp.where(valid, log_cross, -jnp.inf)) * w[None, :]
    Wo0, Wo1, Wo2 = W0[own], W1[own], W2[own]
    h0 = _sum_last(e * Wo0)
    h1 = _sum_last(jnp.where(valid, e * (Wo1 + Wo0 * ell1), 0.0))
    h2 = _sum_last(jnp.where(valid, e * (Wo2 + 2.0 * Wo1 * ell1 + Wo0 * (ell1**2 + ell2)), 0.0))
    pi0, pi1, pi2 = pis
    j_hr = _dot(pi0, h0)
    j_hr1 = _dot(pi1, h0) + _dot(pi0, h1)
    j_hr2 = _dot(pi2, h0) + 2.0 * _dot(pi1, h1) + _dot(pi0, h2)

    # J_hh = πᵀ H π (H symmetric)
    hh_pi0, hh_pi1 = _dot(parts.hh, pi0), _dot(parts.hh, pi1)  # (G,): H π, H π'
    j_hh = _dot(pi0, hh_pi0)
    j_hh1 = 2.0 * _dot(pi1, hh_pi0)
    j_hh2 = 2.0 * _dot(pi2, hh_pi0) + 2.0 * _dot(pi1, hh_pi1)

    n_ref = jnp.sum(gm.mask.astype(jnp.int32))
    n_soft = _dot(pis, parts.counts)
    p1, p2 = _penalty_slopes(n_soft, n_ref, alpha, regularizer)
    f = ise_scale * (j_hh - 2.0 * j_hr + j_rr) + penalty(n_soft[0], n_ref, alpha, regularizer)
    g = ise_scale * (j_hh1 - 2.0 * j_hr1 + j_rr1) + p1
    h = ise_scale * (j_hh2 - 2.0 * j_hr2 + j_rr2) + p2
    return f, g, h


# Newton's evaluation, traced once per mixture shape: the search's loops and batch rules trace it
# again and again (a while_loop under vmap traces its body until the batching settles), which a jit
# answers from its cache; the compiled program is the same (XLA inlines the call)
_relaxed_slopes_jit = jax.jit(
    _relaxed_value_and_slopes, static_argnames=("method", "regularizer", "ise_scale")
)


def relaxed_eise(
    lam: ArrayLike,
    gm: GaussianMixture,
    grid: Array,
    grid_labels: Array,
    grid_counts: Array,
    *,
    temperature: ArrayLike,
    alpha: ArrayLike,
    method: str = "ci",
    regularizer: str = "exp",
    ise_scale: float = 0.5,
) -> Array:
    """The smooth relaxation of the EISE at ``λ`` (module docstring); differentiable in ``λ``.

    Equal (to rounding) to :func:`eise` with ``clip=False`` of the soft clusters
    :func:`merge_membership` makes of :func:`relaxed_membership`'s ``A(λ)``, computed from
    ``λ``-independent per-grid-point sums: ``O(G K d²)`` work per ``λ`` instead of the dense
    soft merge's ``O(K² d³)`` (the module docstring's *Cost*).
    """
    _check_options(method, regularizer)
    parts = _relaxed_parts(gm, grid, grid_labels, grid_counts, method)
    args = (parts, temperature, alpha)
    return _relaxed_at(lam, args, method=method, regularizer=regularizer, ise_scale=ise_scale)


class SearchResult(NamedTuple):
    """Outcome of :func:`search_confidence` (all arrays; batch with vmap).

    Attributes:
        lam: ``()`` the chosen ``λ*``.
        eise: ``()`` hard EISE at ``λ*``.
        labels: ``(K,)`` hard clustering at ``λ*`` (head slots, ``-1`` on padding).
        merged: capacity-``K`` mixture of the merged clusters at ``λ*``, indexed by head slot.
        n_clusters: ``()`` int32 ``N'`` at ``λ*``.
        grid: ``(G,)`` the grid; grid_eise: ``(G,)`` hard EISE on it; grid_counts: ``(G,)`` ``N'``.
        lam_grid: ``()`` the grid's best ``λ``; eise_grid: ``()`` its hard EISE.
        lam_newton: ``()`` where Newton stopped; eise_newton: ``()`` hard EISE there.
        relaxed_newton: ``()`` relaxed EISE there.
        iterations: ``()`` int32 Newton steps taken.
        newton_ok: ``()`` bool, Newton converged (``|Δλ| < tol``) without a failed step.
        used_fallback: ``()`` bool, the grid's best was kept.
    """

    lam: Array
    eise: Array
    labels: Array
    merged: GaussianMixture
    n_clusters: Array
    grid: Array
    grid_eise: Array
    grid_counts: Array
    lam_grid: Array
    eise_grid: Array
    lam_newton: Array
    eise_newton: Array
    relaxed_newton: Array
    iterations: Array
    newton_ok: Array
    used_fallback: Array


def _jvp_slopes(fun, lam, args):
    """Value, first and second derivative of the scalar ``fun(λ, args)``, forward over forward
    (``λ`` is a scalar: the cheapest automatic way)."""

    def value_and_slope(x):
        return jax.jvp(lambda y: fun(y, args), (x,), (jnp.ones_like(x),))

    (f, g), (_, h) = jax.jvp(value_and_slope, (lam,), (jnp.ones_like(lam),))
    return f, g, h


def _try_scale(slopes, k, acc, lam, raw, f, args, lo, hi, start=None):
    """Backtracking's ``k``-th candidate ``λ - raw / 2^k`` (clipped to ``[lo, hi]``), evaluated with its
    slopes (the next step starts from them); ``acc = (found, (λ, f, f', f''))`` takes it if nothing was
    found yet and it does not increase ``f``. Where ``start`` (a run's first pass, :func:`_newton_step`),
    the candidate is ``λ`` itself and is taken."""
    found, best = acc
    cand = jnp.clip(lam - raw * jnp.asarray(0.5, raw.dtype) ** k, lo, hi)  # (a weak 0.5 ** int32 is float64)
    if start is not None:
        cand = jnp.where(start, lam, cand)
    at_cand = (cand, *slopes(cand, args))
    decreases = jnp.isfinite(at_cand[1]) & (at_cand[1] <= f)
    better = (~found) & (decreases if start is None else start | decreases)
    return found | better, tuple(jnp.where(better, a, b) for a, b in zip(at_cand, best))


def _first_where(need: Array, size: int) -> Array:
    """``(size,)`` int32: the indices where ``need`` ``(B,)`` holds, in increasing order, then ``B``
    (out of range: a ``take`` with ``mode="clip"`` reads a real run, a scatter with ``mode="drop"``
    writes nothing). A running count and a scatter: ``argsort(~need, stable=True)`` gives the same
    order but sorts, which on XLA:CPU costs about 0.1 ms for 1000 runs, once per Newton step."""
    B = need.shape[0]
    slot = jnp.where(need, jnp.cumsum(need.astype(jnp.int32)) - 1, size)
    return jnp.full(size, B, jnp.int32).at[slot].set(jnp.arange(B, dtype=jnp.int32), mode="drop")


_HALVING_BLOCK = 32  # runs per block when a batch halves only the runs whose full step was rejected


def _halvings(slopes, n_backtrack: int, k, acc, active, lam, raw, f, args, lo, hi):
    """Backtracking from candidate ``k`` on (:func:`_try_scale`) until one is taken, ``k > n_backtrack``
    or the run is not ``active``; returns ``acc``.

    Alone, a ``while_loop``. Under ``vmap`` the loop would run as long as the batch's slowest run, and
    each pass evaluates the relaxation for the whole batch; a full step is rejected in few runs (on
    the seed 000 jump system at most 0.3 % of the active runs at a step), so the batch rule gathers
    the runs still halving and runs the loop on them alone, in blocks of :data:`_HALVING_BLOCK`
    (usually one block, or none). Each run's arithmetic is the same.
    """

    def alone(k, acc, active, lam, raw, f, args, lo, hi):
        def halve(state):
            k, acc = state
            return k + 1, _try_scale(slopes, k, acc, lam, raw, f, args, lo, hi)

        keep_on = lambda s: (s[0] <= n_backtrack) & ~s[1][0] & active  # noqa: E731
        return jax.lax.while_loop(keep_on, halve, (k, acc))[1]

    batched = jax.custom_batching.custom_vmap(alone)

    @batched.def_vmap
    def _only_those_halving(axis_size, in_batched, *operands):
        spread = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + jnp.shape(a))  # noqa: E731
        operands = jax.tree_util.tree_map(spread, list(operands), list(in_batched))
        k, acc, active = operands[:3]
        out_batched = jax.tree_util.tree_map(lambda _: True, acc)
        if axis_size <= _HALVING_BLOCK:
            return jax.vmap(alone)(*operands), out_batched
        block = _HALVING_BLOCK
        n_blocks = -(-axis_size // block)
        need = (k <= n_backtrack) & ~acc[0] & active
        order = _first_where(need, n_blocks * block)  # the runs still halving, then axis_size

        def one_block(state):
            j, acc = state
            rows = jax.lax.dynamic_slice(order, (j * block,), (block,))
            take = lambda a: jnp.take(a, rows, axis=0, mode="clip")  # noqa: E731
            new = jax.vmap(alone)(*jax.tree_util.tree_map(take, [k, acc, *operands[2:]]))
            return j + 1, jax.tree_util.tree_map(lambda a, b: a.at[rows].set(b, mode="drop"), acc, new)

        n_need = jnp.sum(need.astype(jnp.int32))
        _, acc = jax.lax.while_loop(lambda s: s[0] * block < n_need, one_block, (0, acc))
        return acc, out_batched

    return batched(k, acc, active, lam, raw, f, args, lo, hi)


def _newton_step(slopes, args, lo, hi, tol, radius, n_backtrack: int, early_exit: bool, carry):
    """One damped Newton step of :func:`_newton` on ``carry = (λ, f, f', f'', done, converged,
    iterations, started)``, the slopes those at ``λ``; a run already ``done`` keeps its carry.

    A run not ``started`` yet evaluates its start ``λ`` instead (the first pass of the loop): the
    start and the full steps then share one evaluation in the compiled program (each is a copy of
    the whole relaxed evaluation), and the start counts as no step."""
    lam, f, g, h, done, ok, it, started = carry
    starting = ~started
    active = ~done & started
    finite = jnp.isfinite(g) & jnp.isfinite(h)
    convex = finite & (h > 0)
    raw = jnp.where(convex, g / jnp.where(convex, h, 1.0), jnp.sign(g) * radius)
    # flat to rounding (every grid point near λ clusters alike): g is noise, so stay (and converge)
    flat = jnp.abs(g) * radius <= _FLAT_EPS * jnp.finfo(f.dtype).eps * jnp.abs(f)
    raw = jnp.where(finite & ~flat & started, jnp.clip(raw, -radius, radius), 0.0)

    # a zero step (flat) is taken at once: f re-evaluated at λ in another loop may differ in its last bit
    flat_step = active & finite & (raw == 0)
    # the full step for every run still stepping (or the start), then the halvings where it was rejected;
    # a run not stepping counts as found (it keeps its carry: see `moved`)
    take_full = (active & ~flat_step) | starting
    acc = _try_scale(slopes, 0, (~take_full, (lam, f, g, h)), lam, raw, f, args, lo, hi, start=starting)
    k = jnp.where(take_full & started, 1, n_backtrack + 1).astype(jnp.int32)
    if early_exit:  # only while some run still halves; under vmap, only those runs (_halvings)
        found, new = _halvings(slopes, n_backtrack, k, acc, active, lam, raw, f, args, lo, hi)
    else:  # every halving for every run that stepped (a run that found a candidate keeps it)
        try_scale = partial(_try_scale, slopes, lam=lam, raw=raw, f=f, args=args, lo=lo, hi=hi)
        found, new = jax.lax.fori_loop(1, n_backtrack + 1, try_scale, acc)
    found = found & (finite | starting)
    lam_new, f_new = new[:2]
    small = (jnp.abs(lam_new - lam) < tol) | (jnp.abs(f - f_new) <= tol * jnp.abs(f))
    converged = found & small
    failed = ~found
    moved = (active & found) | starting
    lam_next, f_next, g_next, h_next = (jnp.where(moved, a, b) for a, b in zip(new, (lam, f, g, h)))
    done_next = done | (active & (converged | failed))
    ok_next = jnp.where(active, converged, ok)
    return (
        lam_next,
        f_next,
        g_next,
        h_next,
        done_next,
        ok_next,
        it + active.astype(jnp.int32),
        started | starting,
    )


def _newton_loop(slopes, steps: int, n_backtrack: int, early_exit: bool, args, lam0, lo, hi, tol, radius):
    """:func:`_newton`'s iteration: a ``while_loop`` that stops once every run is done
    (``early_exit``; :func:`_step_until_done`), or a ``scan`` of ``steps + 1`` passes
    (reverse-differentiable); equal values. The first pass evaluates the start (:func:`_newton_step`)."""
    if early_exit:
        lam, f, *_, ok, it, _ = _step_until_done(slopes, steps, n_backtrack, args, lam0, lo, hi, tol, radius)
        return lam, f, ok, it
    step = partial(_newton_step, slopes, args, lo, hi, tol, radius, n_backtrack, early_exit)
    (lam, f, *_, ok, it, _), _ = jax.lax.scan(
        lambda c, _: (step(c), None), _newton_start(lam0), None, length=steps + 1
    )
    return lam, f, ok, it


def _newton_start(lam0) -> tuple:
    """The carry of :func:`_newton_step` before the first pass (``f``, ``f'``, ``f''`` unset until
    that pass evaluates the start)."""
    lam0 = jnp.asarray(lam0)
    unset = jnp.zeros_like(lam0)
    false, zero = jnp.zeros((), bool), jnp.zeros((), jnp.int32)
    return (lam0, unset, unset, unset, false, false, zero, false)


_STEP_CHUNKS = 4  # under vmap, a Newton pass steps the batch's runs still stepping in chunks of a quarter
_STEP_CHUNK_MIN = 64  # of the batch, at least this many runs (batches up to twice this step whole)


def _step_until_done(slopes, steps: int, n_backtrack: int, args, lam0, lo, hi, tol, radius) -> tuple:
    """:func:`_newton_step` from :func:`_newton_start` until the run is done or has taken ``steps``
    steps; the final carry.

    Alone, a ``while_loop``. Under ``vmap`` a ``while_loop`` runs every run in every pass until the
    batch's slowest run is done, and on the seed 000 jump system a third to a half of the runs
    stop after the first step while 13–47 % take all 8 (docs/scaling.md), so the batch rule gathers
    the runs still stepping at each pass and steps them in chunks of a quarter of the batch (at
    least :data:`_STEP_CHUNK_MIN` runs; usually as many chunks as a quarter of the runs still
    stepping, rounded up). A run's arithmetic is the same in a chunk as in the whole batch (the
    relaxed slopes sum in a fixed order from 32 runs up).
    """
    keep_on = lambda c: ~c[7] | (~c[4] & (c[6] < steps))  # noqa: E731  (not started, or still stepping)

    def step(args, lo, hi, tol, radius, carry):
        return _newton_step(slopes, args, lo, hi, tol, radius, n_backtrack, True, carry)

    def alone(args, lam0, lo, hi, tol, radius):
        return jax.lax.while_loop(keep_on, partial(step, args, lo, hi, tol, radius), _newton_start(lam0))

    batched = jax.custom_batching.custom_vmap(alone)

    @batched.def_vmap
    def _only_those_stepping(axis_size, in_batched, *operands):
        # the operands the batch shares stay shared (a constant τ stays a constant to XLA, which
        # may round its arithmetic differently from that of an array of τ's)
        axes = jax.tree_util.tree_map(lambda b: 0 if b else None, list(in_batched))
        out_batched = tuple(True for _ in range(8))
        if axis_size <= 2 * _STEP_CHUNK_MIN:
            return jax.vmap(alone, in_axes=axes)(*operands), out_batched
        args, lam0, lo, hi, tol, radius = operands
        fixed, fixed_axes = (args, lo, hi, tol, radius), (axes[0], *axes[2:])
        if axes[1] is None:
            lam0 = jnp.broadcast_to(lam0, (axis_size,) + jnp.shape(lam0))
        chunk = max(-(-axis_size // _STEP_CHUNKS), _STEP_CHUNK_MIN)
        n_chunks = -(-axis_size // chunk)

        def one_pass(carry):
            stepping = keep_on(carry)
            order = _first_where(stepping, n_chunks * chunk)

            def one_chunk(state):
                j, carry = state
                rows = jax.lax.dynamic_slice(order, (j * chunk,), (chunk,))
                take = lambda axis, a: a if axis is None else jnp.take(a, rows, axis=0, mode="clip")  # noqa: E731
                gathered = jax.tree_util.tree_map(take, fixed_axes, fixed, is_leaf=lambda x: x is None)
                carry_rows = jax.tree_util.tree_map(lambda a: jnp.take(a, rows, axis=0, mode="clip"), carry)
                new = jax.vmap(step, in_axes=(*fixed_axes, 0))(*gathered, carry_rows)
                return j + 1, jax.tree_util.tree_map(lambda a, b: a.at[rows].set(b, mode="drop"), carry, new)

            n_stepping = jnp.sum(stepping.astype(jnp.int32))
            return jax.lax.while_loop(lambda s: s[0] * chunk < n_stepping, one_chunk, (0, carry))[1]

        start = jax.vmap(_newton_start)(lam0)
        return jax.lax.while_loop(lambda c: jnp.any(keep_on(c)), one_pass, start), out_batched

    return batched(args, lam0, lo, hi, tol, radius)


@partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2, 3))
def _newton_early_exit(slopes, steps: int, n_backtrack: int, differentiable, args, lam0, lo, hi, tol, radius):
    return _newton_loop(slopes, steps, n_backtrack, True, args, lam0, lo, hi, tol, radius)


@_newton_early_exit.defjvp
def _newton_early_exit_jvp(slopes, steps, n_backtrack, differentiable, primals, tangents):
    # differentiate the fixed-length scan: the same values, and reverse mode (a while_loop has none)
    (args, *rest), (args_dot, *rest_dot) = primals, tangents
    primals = (differentiable(args), *rest)
    tangents = (differentiable(args_dot), *rest_dot)
    return jax.jvp(partial(_newton_loop, slopes, steps, n_backtrack, False), primals, tangents)


def _newton(
    fun,
    args,
    lam0,
    lo,
    hi,
    steps: int,
    tol,
    radius,
    n_backtrack: int = 4,
    slopes=None,
    differentiable=lambda args: args,
):
    """Damped Newton–Raphson on the scalar function ``fun(λ, args)`` over ``[lo, hi]``.

    Each step is the Newton step ``g / h`` (or, where the curvature is not positive, a descent step
    of length ``radius``), clipped to the trust radius ``radius`` and halved up to ``n_backtrack``
    times until the function decreases. Where ``|g| radius <= 64 ε |f|`` the function is flat to
    rounding (for the relaxed EISE: every grid point near ``λ`` clusters alike) and ``g`` is noise:
    no step is taken and Newton has converged where it is. It stops when ``|Δλ| < tol`` or the relative change of the
    function is below ``tol`` (seed 000 Fig. 2: "the change of the adjacent EISE is less than a
    small value") — *converged* — or when no halving decreases the function or a derivative is not
    finite — *failed* — or after ``steps`` steps.

    Every candidate is evaluated with its derivatives (``slopes``), so the step after an accepted
    candidate starts from them: one evaluation per step where the full step decreases the
    function (nearly always; the halvings are rare), instead of the derivatives at ``λ`` and the
    value at the candidate apart. The start is evaluated by the loop's first pass, so the compiled
    program holds two copies of the evaluation (the step loop's and the halving blocks'), not three.

    The loops exit early: the step loop once the run is done, the halvings once a candidate
    decreases ``fun``. Under ``vmap`` each pass of the step loop steps only the runs still stepping,
    gathered into chunks of a quarter of the batch (:func:`_step_until_done`), until every run is
    done, and only the runs whose full step was rejected halve, gathered into blocks
    (:func:`_halvings`). ``while_loop`` has no reverse mode, so a custom JVP differentiates the
    equivalent fixed-length ``scan`` instead: the values are identical (bitwise in
    ``tests/test_pcm.py``; compiled inside the whole search, XLA may fuse the two differently, and
    on 4 × 1000 jump-system searches 0–4 runs' ``λ`` differed by up to 1e-14 relative) and the
    derivatives are those of the ``scan`` (``jax.grad`` works).
    ``fun`` must take everything it differentiates through ``args`` (a pytree), not a closure.
    ``slopes(λ, args) -> (f, f', f'')`` gives the value and derivatives (default:
    forward-over-forward ``jvp`` of ``fun``).
    ``differentiable(args)``: the ``args`` (and their tangents) the differentiated ``scan`` takes,
    the same arithmetic (:func:`search_confidence` drops :class:`_Pairs`, whose loop has no reverse
    mode: the scan's values then equal the loop's to rounding).

    Returns:
        ``(λ, fun(λ), converged, iterations)``.
    """
    slopes = partial(_jvp_slopes, fun) if slopes is None else slopes
    return _newton_early_exit(slopes, steps, n_backtrack, differentiable, args, lam0, lo, hi, tol, radius)


_CLUSTER_BLOCK = 16  # runs per block when a batch clusters only the runs that need it


def _cluster_unless_known(cluster, known: Array, known_labels: Array, *operands) -> Array:
    """``cluster(*operands)``'s labels ``(K,)``, or ``known_labels`` where ``known`` says they are
    equal already (:func:`search_confidence`: Newton's ``λ`` has the judgment matrix of a grid point).

    Alone, a ``cond`` skips the overlap sweep. Under ``vmap`` a ``cond`` runs both sides and the
    sweep runs as long as its slowest run, so the batch rule gathers the runs that need a clustering
    and sweeps them in blocks of :data:`_CLUSTER_BLOCK` (usually one block, or none). The labels
    are integers of a piecewise-constant map: no derivative flows through them.
    """
    operands = jax.lax.stop_gradient(operands)

    def alone(known, known_labels, *operands):
        return jax.lax.cond(known, lambda: known_labels, lambda: cluster(*operands))

    batched = jax.custom_batching.custom_vmap(alone)

    @batched.def_vmap
    def _only_those_needed(axis_size, in_batched, known, known_labels, *operands):
        spread = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + jnp.shape(a))  # noqa: E731
        known, labels, *operands = jax.tree_util.tree_map(
            spread, [known, known_labels, *operands], list(in_batched)
        )
        if axis_size == 0:
            return labels, True
        block = min(_CLUSTER_BLOCK, axis_size)
        n_blocks = -(-axis_size // block)
        need = ~known
        order = _first_where(need, n_blocks * block)  # the runs that need a clustering, then axis_size

        def one_block(state):
            j, labels = state
            rows = jax.lax.dynamic_slice(order, (j * block,), (block,))
            take = lambda a: jnp.take(a, rows, axis=0, mode="clip")  # noqa: E731
            new = jax.vmap(cluster)(*jax.tree_util.tree_map(take, operands))
            new = jnp.where(take(need)[:, None], new, take(labels))
            return j + 1, labels.at[rows].set(new, mode="drop")

        n_need = jnp.sum(need.astype(jnp.int32))
        _, labels = jax.lax.while_loop(lambda s: s[0] * block < n_need, one_block, (0, labels))
        return labels, True

    return batched(known, known_labels, *operands)


@partial(
    jax.jit,
    static_argnames=(
        "grid_size",
        "newton_steps",
        "method",
        "regularizer",
        "ise_scale",
        "dims",
        "triangular",
        "subset_rule",
    ),
)
def search_confidence(
    gm: GaussianMixture,
    *,
    lam_lo: ArrayLike,
    lam_hi: ArrayLike,
    grid_size: int,
    newton_steps: int,
    temperature: ArrayLike,
    tol: ArrayLike,
    alpha: ArrayLike,
    method: str = "ci",
    regularizer: str = "exp",
    ise_scale: float = 0.5,
    dims: Sequence[int] | None = None,
    triangular: bool = False,
    subset_rule: str = "split",
    range_scale: ArrayLike = 0.5,
) -> SearchResult:
    """Search the confidence multiplier ``λ`` minimising the EISE (seed 000 Table 1 step 7).

    (a) Hard EISE on a grid of ``grid_size`` points over ``[lam_lo, lam_hi]`` (seed 000: ``[1, 3]``;
    seed 003: ``[0.5, 3]``); (b) ``newton_steps`` Newton–Raphson steps on the relaxed EISE from the
    grid's best (``newton_steps = 0`` skips them), falling back to the grid's best unless Newton
    converged to a ``λ`` whose *hard* EISE is no worse. See the module docstring.

    Args:
        gm: mixture of capacity ``K`` to cluster (pruned already, weights normalised).
        lam_lo, lam_hi: search scope. grid_size: static ``G >= 2``. newton_steps: static.
        temperature: relaxation temperature ``τ`` (about the grid spacing); also Newton's trust
            radius.
        tol: Newton stops when ``|Δλ| < tol`` or the relative change of the relaxed EISE is below.
        alpha, method, regularizer, ise_scale: see :func:`eise` / :func:`merge_membership`.
        dims, triangular, subset_rule, range_scale: see :func:`gmjax.reduction.clustering.gauss_cluster`.
    """
    _check_options(method, regularizer)
    if grid_size < 2:
        raise ValueError(f"grid_size: must be >= 2, got {grid_size}")
    if newton_steps < 0:
        raise ValueError(f"newton_steps: must be >= 0, got {newton_steps}")
    dtype = gm.means.dtype
    delta = similarity_thresholds(gm, dims)
    dist = centre_distances(gm, dims)
    lo = jnp.asarray(lam_lo, dtype)
    hi = jnp.asarray(lam_hi, dtype)
    grid = lo + (hi - lo) * jnp.linspace(0.0, 1.0, grid_size, dtype=dtype)
    # the clustering-independent parts of every grid point's EISE and merge, once
    overlaps = self_overlaps(gm)
    info = gaussian.spd_inv(gm.covs) if method == "ci" else None

    def cluster(gm, lam, delta, dist, range_scale):
        return gauss_cluster(
            gm,
            lam,
            triangular=triangular,
            subset_rule=subset_rule,
            range_scale=range_scale,
            delta=delta,
            dist=dist,
        )

    def evaluate_labels(labels):
        value, merged, n = hard_eise(
            gm,
            labels,
            alpha=alpha,
            method=method,
            regularizer=regularizer,
            ise_scale=ise_scale,
            overlaps=overlaps,
            info=info,
        )
        return value, labels, merged, n

    # all grid clusterings in one overlap sweep, then the grid's merges and EISEs side by side
    grid_clusters = cluster(gm, grid, delta, dist, range_scale)
    grid_eise, grid_labels, grid_merged, grid_counts = jax.vmap(evaluate_labels)(grid_clusters.labels)
    best = jnp.argmin(grid_eise)
    lam_grid = grid[best]
    eise_grid = grid_eise[best]
    labels_grid = grid_labels[best]
    merged_grid = jax.tree_util.tree_map(lambda a: a[best], grid_merged)
    n_grid = grid_counts[best]

    if newton_steps == 0:
        zero_i = jnp.zeros((), jnp.int32)
        return SearchResult(
            lam_grid,
            eise_grid,
            labels_grid,
            merged_grid,
            n_grid,
            grid,
            grid_eise,
            grid_counts,
            lam_grid,
            eise_grid,
            lam_grid,
            eise_grid,
            jnp.asarray(jnp.nan, dtype),
            zero_i,
            jnp.zeros((), bool),
            jnp.ones((), bool),
        )

    parts = _relaxed_parts(
        gm, grid, grid_labels, grid_counts, method, overlaps=overlaps, info=info, distinct_pairs=True
    )

    relaxed = partial(_relaxed_at, method=method, regularizer=regularizer, ise_scale=ise_scale)
    slopes = partial(_relaxed_slopes_jit, method=method, regularizer=regularizer, ise_scale=ise_scale)
    tau = jnp.asarray(temperature, dtype)
    lam_newton, relaxed_newton, newton_ok, iterations = _newton(
        relaxed,
        (parts, tau, jnp.asarray(alpha, dtype)),
        lam_grid,
        lo,
        hi,
        newton_steps,
        jnp.asarray(tol, dtype),
        tau,
        slopes=slopes,
        differentiable=lambda args: (args[0]._replace(pairs=None), *args[1:]),
    )
    # the clustering depends on λ only through the judgment matrix, and a judgment matrix grows
    # with λ (r_ij = [δ_ij <= s λ]): as many entries as a grid point's means the same matrix
    entries = lambda r: jnp.sum(r.astype(jnp.int32), axis=(-2, -1))  # noqa: E731
    newton_judgment = judgment_matrix(
        delta, jnp.asarray(range_scale, dtype) * lam_newton, gm.mask, triangular=triangular
    )
    same = entries(grid_clusters.judgment) == entries(newton_judgment)  # (G,)
    labels_known = grid_labels[jnp.argmax(same)]
    newton_labels = _cluster_unless_known(
        lambda *a: cluster(*a).labels, jnp.any(same), labels_known, gm, lam_newton, delta, dist, range_scale
    )
    eise_newton, labels_newton, merged_newton, n_newton = evaluate_labels(newton_labels)
    slack = 8 * jnp.finfo(dtype).eps * jnp.abs(eise_grid)  # rounding of an identical clustering
    use_newton = newton_ok & (eise_newton <= eise_grid + slack)
    pick = lambda a, b: jnp.where(use_newton, a, b)  # noqa: E731
    return SearchResult(
        lam=pick(lam_newton, lam_grid),
        eise=pick(eise_newton, eise_grid),
        labels=pick(labels_newton, labels_grid),
        merged=jax.tree_util.tree_map(pick, merged_newton, merged_grid),
        n_clusters=pick(n_newton, n_grid),
        grid=grid,
        grid_eise=grid_eise,
        grid_counts=grid_counts,
        lam_grid=lam_grid,
        eise_grid=eise_grid,
        lam_newton=lam_newton,
        eise_newton=eise_newton,
        relaxed_newton=relaxed_newton,
        iterations=iterations,
        newton_ok=newton_ok,
        used_fallback=~use_newton,
    )
