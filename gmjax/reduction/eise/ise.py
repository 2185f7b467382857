"""The EISE of a hard clustering in closed form (seed 000 eqs 29–35, seed 003 eqs 10–15): the
fractional or one-hot merge of each cluster, the ISE between a cluster and its merge, the penalty on
the number of clusters."""

from __future__ import annotations

import functools
from functools import partial

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._types import Array, ArrayLike, DTypeLike
from gmjax.mixture import GaussianMixture

__all__ = [
    "onehot_membership",
    "merge_membership",
    "cluster_ise",
    "self_overlaps",
    "eise",
    "penalty",
    "hard_eise",
]

_METHODS = ("ci", "moment")
_REGULARIZERS = ("exp", "log10")


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


def _merge_hard_ci(gm: GaussianMixture, labels: Array, info: Array | None = None) -> GaussianMixture:
    """:func:`merge_membership` ``"ci"`` of a hard clustering (``labels`` ``(K,)``, the head slot of
    each component, ``-1`` for none) by per-cluster sums (:func:`_cluster_sums`): ``P̄_c^{-1} =
    Σ_{m ∈ c} (w_m / W_c) P_m^{-1}``, ``ū_c = P̄_c Σ_{m ∈ c} (w_m / W_c) P_m^{-1} u_m`` (seed 000
    eqs 38–39), as the numba reference loop forms them. ``O(K d²)`` additions instead of the one-hot
    product's ``O(K² d²)`` multiply-adds; the same merge to rounding. ``info``: ``P_m^{-1}``."""
    dtype = gm.means.dtype
    K, d = gm.capacity, gm.dim
    lab = jnp.where(gm.mask, labels, -1)
    w = jnp.where(lab >= 0, gm.weights, 0.0).astype(dtype)
    W = _cluster_sums(w, lab, K)
    live = W > 0
    W_own = W[jnp.maximum(lab, 0)]
    frac = jnp.where(lab >= 0, w / jnp.where(W_own > 0, W_own, 1.0), 0.0)
    info = gaussian.spd_inv(gm.covs) if info is None else info
    info = jnp.where(gm.mask[:, None, None], info, 0.0)
    eta = jnp.einsum("kij,kj->ki", info, gm.means)  # P⁻¹u
    eye = jnp.eye(d, dtype=dtype)
    info_c = jnp.where(live[:, None, None], _cluster_sums(frac[:, None, None] * info, lab, K), eye)
    eta_c = _cluster_sums(frac[:, None] * eta, lab, K)
    cov = gaussian.spd_inv(info_c)
    mu = jnp.einsum("cij,cj->ci", cov, eta_c)
    mu = jnp.where(live[:, None], mu, 0.0)
    cov = jnp.where(live[:, None, None], cov, eye)
    return GaussianMixture(jnp.where(live, W, 0.0), mu, cov, live)


def _merge_hard(
    gm: GaussianMixture, labels: Array, method: str, info: Array | None = None
) -> GaussianMixture:
    """The merge of a hard clustering as :func:`hard_eise` forms it (``"ci"``: :func:`_merge_hard_ci`;
    ``"moment"``: :func:`merge_membership` of the one-hot membership), capacity ``K``."""
    if method == "ci":
        return _merge_hard_ci(gm, labels, info)
    return merge_membership(gm, onehot_membership(labels, gm.capacity, gm.means.dtype), method)


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
    merged = _merge_hard(gm, labels, method, info)
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
