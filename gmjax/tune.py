"""Smooth relaxations of thresholded decisions, and an optax loop that tunes thresholds by gradient.

Every reduction threshold of the papers (``ρ`` of the censored pruning, seed 000 eqs 19–22; ``λ`` of
the similarity clustering, eqs 23–28; a weight threshold; the split threshold ``ψ_th`` of seed 001
eq 31) makes a *hard* decision, so a Monte Carlo loss is piecewise constant in it and its gradient is
0 almost everywhere. This module replaces each decision by a relaxation with a temperature ``T``:

* :func:`soft_step` — the relaxed Heaviside step ``σ(x / T)``; ``T = 0`` is the hard step exactly.
* :func:`threshold_gates`, :func:`censored_gates` — soft pruning gates; a gated component's weight is
  scaled by its gate and the survivors are renormalised (:func:`gated_prune`). :class:`SoftPruneThreshold`
  and :class:`SoftPruneCensored` are the relaxed reducers.
* :func:`soft_membership` — soft similarity memberships: the kernel-smoothed clustering
  ``A(λ) = Σ_g π_g(λ) A_g`` over a fixed grid of ``λ`` that PCM's Newton search already uses
  (:func:`gmjax.reduction._eise.relaxed_membership`); :class:`SoftPCM` is PCM at a given ``λ`` with
  soft pruning and soft memberships.
* :func:`soft_split_gate` — the soft split trigger for :mod:`gmjax.filters.agsf`: a ``(ψ, ψ_th) -> gate``
  function whose gate scales the split displacement.

Each relaxation has three modes (static): ``"hard"`` (the original decision), ``"soft"`` (the
relaxation; ``T = 0`` reproduces ``"hard"`` exactly) and ``"straight_through"`` (hard forward pass,
the relaxation's gradient: ``hard + (soft - stop_gradient(soft))``, whose value is exactly ``hard``).

:func:`tune` runs the loop: each step simulates a batched Monte Carlo study with the current
thresholds, differentiates a loss (:func:`armse_loss`, :func:`anees_loss`, :func:`aeise_loss`,
:func:`count_loss`, :func:`weighted_loss`) and applies an optax update to unconstrained parameters
that are mapped into each threshold's valid range (:class:`Bounds`). :func:`plot_history` plots it.
"""

from __future__ import annotations

import math
import sys
import time
from functools import partial
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import metrics
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array, ArrayLike, PRNGKey
from gmjax.filters._core import Filter
from gmjax.mixture import GaussianMixture, sanitize
from gmjax.models._base import Scenario
from gmjax.reduction import _util
from gmjax.reduction._base import ReductionInfo, make_info
from gmjax.reduction._clustering import centre_distances, gauss_cluster, similarity_thresholds
from gmjax.reduction._eise import eise, hard_eise, merge_membership, onehot_membership, relaxed_membership
from gmjax.reduction._merge import merge_labels
from gmjax.reduction._prune import select_kept

__all__ = [
    "MODES",
    "soft_step",
    "threshold_gates",
    "censored_gates",
    "gated_prune",
    "soft_prune_threshold",
    "soft_prune_censored",
    "SoftPruneThreshold",
    "SoftPruneCensored",
    "soft_membership",
    "soft_pcm",
    "SoftPCM",
    "soft_split_gate",
    "Bounds",
    "TuneScores",
    "TuneHistory",
    "TuneResult",
    "study_scores",
    "armse_loss",
    "anees_loss",
    "aeise_loss",
    "count_loss",
    "weighted_loss",
    "tune",
    "plot_history",
]

MODES = ("hard", "soft", "straight_through")


def _check_mode(mode: str) -> None:
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")


def _check_temperature(temperature: Any, name: str = "temperature") -> None:
    _util.validate_nonneg(temperature, name, allow_inf=False)


def _straight_through(hard: Array, soft: Array) -> Array:
    """Value exactly ``hard`` (``soft - soft`` is exactly 0), gradient of ``soft``."""
    return hard + (soft - jax.lax.stop_gradient(soft))


# ----------------------------------------------------------------------------- the relaxed step


def soft_step(x: ArrayLike, temperature: ArrayLike, *, mode: str = "soft", strict: bool = False) -> Array:
    """Relaxed Heaviside step of ``x`` (elementwise).

    ``hard = [x > 0]`` if ``strict`` else ``[x >= 0]``; ``soft = σ(x / T)`` for ``T > 0`` and
    ``hard`` for ``T = 0`` (so ``T = 0`` is the hard decision exactly, ties included); the
    straight-through value is ``hard`` with the gradient of ``σ(x / T)``. ``T`` is in the units of
    ``x``. Gradients are finite at ``T = 0`` too (the division is guarded on both sides).

    Args:
        x: decision margin (``>= 0`` means "keep"/"trigger"), any shape.
        temperature: ``()`` ``T >= 0``, may be traced.
        mode: ``"hard"``, ``"soft"`` or ``"straight_through"`` (static).
        strict: the hard step is ``x > 0`` instead of ``x >= 0``.
    """
    _check_mode(mode)
    x = jnp.asarray(x)
    dtype = x.dtype if jnp.issubdtype(x.dtype, jnp.floating) else jnp.result_type(float)
    x = x.astype(dtype)
    hard = ((x > 0) if strict else (x >= 0)).astype(dtype)
    if mode == "hard":
        return hard
    T = jnp.asarray(temperature, dtype)
    pos = T > 0
    soft = jnp.where(pos, jax.nn.sigmoid(x / jnp.where(pos, T, 1.0)), hard)
    if mode == "soft":
        return soft
    return _straight_through(hard, soft)


# ----------------------------------------------------------------------------- soft pruning


def threshold_gates(gm: GaussianMixture, threshold: ArrayLike, temperature: ArrayLike, *,
                    mode: str = "soft") -> Array:
    """``(K,)`` gates of weight-threshold pruning: ``σ((w_k - threshold) / T)``, 0 on padding.

    The hard gate ``[w_k >= threshold]`` is :func:`gmjax.reduction.prune_threshold`'s rule; ``T`` is
    in weight units.
    """
    w = jnp.where(gm.mask, gm.weights, 0.0)
    g = soft_step(w - jnp.asarray(threshold, w.dtype), temperature, mode=mode)
    return jnp.where(gm.mask, g, 0.0)


def censored_gates(gm: GaussianMixture, rho: ArrayLike, temperature: ArrayLike, *,
                   max_components: int | None = None, mode: str = "soft") -> Array:
    """``(K,)`` gates of the j-th order statistic censored pruning (seed 000 eqs 19–22).

    With the live weights in descending order, the component of rank ``r`` (0-based) survives the
    hard rule iff ``c_r < ρ W`` where ``c_r`` is the mass of the ``r`` heavier components and ``W``
    the total: this is eqs 20–22 (``N`` = the smallest count whose largest weights hold ``ρ`` of the
    total; see :func:`gmjax.reduction._prune.censored_count`). The relaxed gate is
    ``σ((ρ W - c_r) / T)`` (``T`` in units of probability mass); the heaviest component always
    survives (gate 1, as in the hard rule), and ranks ``>= N_u`` (``max_components``, eq 22) are
    always pruned. Ties are ranked by slot index, as in the hard rule.
    """
    w = jnp.where(gm.mask, gm.weights, 0.0)
    total = jnp.sum(w)
    order = jnp.argsort(-jnp.where(gm.mask, w, -jnp.inf), stable=True)
    K = gm.capacity
    rank = jnp.zeros(K, jnp.int32).at[order].set(jnp.arange(K, dtype=jnp.int32))
    desc = w[order]
    heavier = jnp.cumsum(desc) - desc  # exclusive cumulative mass, by rank
    g_rank = soft_step(jnp.asarray(rho, w.dtype) * total - heavier, temperature, mode=mode, strict=True)
    ranks = jnp.arange(K)
    g_rank = jnp.where(ranks == 0, jnp.ones_like(g_rank), g_rank)
    if max_components is not None:
        g_rank = jnp.where(ranks < max_components, g_rank, 0.0)
    return jnp.where(gm.mask, g_rank[rank], 0.0)


def _negligible_floor(temperature: ArrayLike, mode: str, dtype) -> Array:
    """``eps²`` for a relaxed (``"soft"``, ``T > 0``) gate, else 0 (see :func:`gated_prune`)."""
    eps2 = jnp.asarray(jnp.finfo(dtype).eps ** 2, dtype)
    if mode != "soft":
        return jnp.zeros((), dtype)
    return jnp.where(jnp.asarray(temperature, dtype) > 0, eps2, 0.0)


@partial(jax.jit, static_argnames=("capacity",))
def gated_prune(gm: GaussianMixture, gates: Array, capacity: int,
                floor: ArrayLike = 0.0) -> tuple[GaussianMixture, ReductionInfo]:
    """Scale every weight by its gate, drop gate-0 slots, keep the heaviest ``capacity``, renormalise.

    With 0/1 gates this is exactly the hard pruning of :mod:`gmjax.reduction._prune` (same slot
    order: survivors heaviest first, ties by slot; survivors scaled to the input's total weight,
    seed 000 eq 41; if nothing survives the heaviest component is kept). With soft gates a
    component's weight becomes ``g_k w_k W / Σ_j g_j w_j``: every weight is a smooth function of
    the gates.

    ``floor``: slots whose gated weight ``g_k w_k`` is below ``floor · W`` are dropped as well. The
    relaxed reducers pass ``eps²`` of the dtype when ``T > 0`` (0 otherwise, so ``T = 0`` stays
    exact): such a component is below rounding in every output, but a soft gate would keep it live,
    and merging it alone (weight ``~1e-160``) squares its weight in the derivative of ``ω / W``,
    which underflows to a non-finite gradient.

    Returns:
        ``(pruned, info)``; ``info.aux`` holds ``gates`` (``(capacity,)``, the output slots' gates)
        and ``n_expected`` (``Σ_k g_k``, the expected number of survivors).
    """
    w = jnp.where(gm.mask, gm.weights, 0.0)
    total = jnp.sum(w)
    gates = jnp.where(gm.mask, gates.astype(w.dtype), 0.0)
    keep = gm.mask & (gates > 0) & ~(gates * w < jnp.asarray(floor, w.dtype) * total)
    K = gm.capacity
    heaviest = jnp.argmax(jnp.where(gm.mask, w, -jnp.inf))
    rescue = ~jnp.any(keep)
    keep = jnp.where(rescue, jnp.arange(K) == heaviest, keep)
    gates = jnp.where(rescue & (jnp.arange(K) == heaviest), 1.0, gates)
    n_keep = jnp.sum(keep.astype(jnp.int32))
    idx, sel_valid, labels = select_kept(gm, keep, w, capacity)
    out = jax.tree_util.tree_map(lambda a: a[idx], gm)
    g_out = jnp.where(sel_valid, gates[idx], 0.0)
    gw = out.weights * g_out
    kept_mass = jnp.sum(jnp.where(sel_valid, gw, 0.0))
    ok = kept_mass > 0
    scale = jnp.where(ok, total / jnp.where(ok, kept_mass, 1.0), 1.0)
    out = sanitize(out._replace(weights=gw * scale, mask=sel_valid))
    info = make_info(gm, out, labels, pruned_mass=total - kept_mass, overflow=n_keep > capacity,
                     aux={"scale": scale, "gates": g_out, "n_expected": jnp.sum(gates)})
    return out, info


def soft_prune_threshold(gm: GaussianMixture, threshold: ArrayLike, *, temperature: ArrayLike = 0.0,
                         mode: str = "soft", capacity: int | None = None,
                         key: PRNGKey | None = None) -> tuple[GaussianMixture, ReductionInfo]:
    """Relaxed :func:`gmjax.reduction.prune_threshold` (``T = 0`` or ``mode="hard"``: identical).

    Args:
        gm: input mixture, capacity ``K``.
        threshold: ``()`` weight threshold ``>= 0`` (traced).
        temperature: ``()`` ``T >= 0`` in weight units (traced).
        mode: ``"hard"``, ``"soft"`` or ``"straight_through"`` (static).
        capacity: static output capacity (default ``K``).
        key: unused (Reducer protocol).
    """
    del key
    _util.validate_mixture(gm)
    _util.validate_nonneg(threshold, "threshold")
    _check_temperature(temperature)
    _check_mode(mode)
    cap = _util.validate_capacity(capacity, gm)
    floor = _negligible_floor(temperature, mode, gm.weights.dtype)
    return gated_prune(gm, threshold_gates(gm, threshold, temperature, mode=mode), cap, floor)


def soft_prune_censored(gm: GaussianMixture, rho: ArrayLike = 0.9544, max_components: int | None = None, *,
                        temperature: ArrayLike = 0.0, mode: str = "soft", capacity: int | None = None,
                        key: PRNGKey | None = None) -> tuple[GaussianMixture, ReductionInfo]:
    """Relaxed :func:`gmjax.reduction.prune_censored` (seed 000 eqs 19–22, 41; ``T = 0``: identical).

    Args:
        gm: input mixture, capacity ``K``.
        rho: ``ρ`` in ``[0, 1]`` (traced).
        max_components: static cap ``N_u`` (eq 22).
        temperature: ``()`` ``T >= 0`` in units of probability mass (traced).
        mode: ``"hard"``, ``"soft"`` or ``"straight_through"`` (static).
        capacity: static output capacity (default ``K``).
        key: unused.
    """
    del key
    _util.validate_mixture(gm)
    _util.validate_range(rho, "rho", 0.0, 1.0)
    _check_temperature(temperature)
    _check_mode(mode)
    if max_components is not None:
        max_components = _util.validate_count(max_components, "max_components", 1, 2**31 - 1)
    cap = _util.validate_capacity(capacity, gm)
    gates = censored_gates(gm, rho, temperature, max_components=max_components, mode=mode)
    return gated_prune(gm, gates, cap, _negligible_floor(temperature, mode, gm.weights.dtype))


@pytree_dataclass
class SoftPruneThreshold:
    """Reducer config for :func:`soft_prune_threshold` (``threshold``, ``temperature`` traced)."""

    threshold: Any = 1e-5
    temperature: Any = 0.0
    mode: str = static_field("soft")
    capacity: int | None = static_field(None)

    def __call__(self, gm, *, key=None):
        return soft_prune_threshold(gm, self.threshold, temperature=self.temperature, mode=self.mode,
                                    capacity=self.capacity, key=key)


@pytree_dataclass
class SoftPruneCensored:
    """Reducer config for :func:`soft_prune_censored` (``rho``, ``temperature`` traced)."""

    rho: Any = 0.9544
    temperature: Any = 0.0
    max_components: int | None = static_field(None)
    mode: str = static_field("soft")
    capacity: int | None = static_field(None)

    def __call__(self, gm, *, key=None):
        return soft_prune_censored(gm, self.rho, self.max_components, temperature=self.temperature,
                                   mode=self.mode, capacity=self.capacity, key=key)


# ----------------------------------------------------------------------------- soft memberships


def soft_membership(gm: GaussianMixture, lam: ArrayLike, grid: Array, temperature: ArrayLike, *,
                    dims: Sequence[int] | None = None, range_scale: ArrayLike = 0.5,
                    triangular: bool = False, subset_rule: str = "split") -> tuple[Array, Array, Array, Array]:
    """Soft similarity memberships at ``λ``, shared with PCM's confidence search.

    The hard clustering (seed 000 eqs 23–28, :func:`gmjax.reduction.gauss_cluster`) is piecewise
    constant in ``λ``. As in PCM's Newton search (:mod:`gmjax.reduction._eise`), the relaxation is the
    kernel-smoothed clustering over a *fixed* grid ``λ_1 < … < λ_G``:
    ``A(λ) = Σ_g π_g(λ) A_g`` with ``π(λ) = softmax(-(λ - λ_g)² / 2T²)`` and ``A_g`` the one-hot
    clustering at ``λ_g``; it is smooth in ``λ`` for ``T > 0``. At ``T = 0`` the membership is the hard
    clustering at ``λ`` itself (not the nearest grid point), so ``T = 0`` is the hard rule exactly.

    Args:
        gm: mixture of capacity ``K`` (only means, covariances and mask are used; no gradient flows
            through the discrete clustering).
        lam: ``()`` confidence multiplier (traced).
        grid: ``(G,)`` fixed grid of ``λ`` (e.g. the search scope ``[1, 3]``).
        temperature: ``()`` ``T >= 0`` in units of ``λ`` (about the grid spacing).
        dims, range_scale, triangular, subset_rule: as in :func:`gmjax.reduction.gauss_cluster`.

    Returns:
        ``(A, pi, grid_labels, labels)``: ``A`` ``(K, K)`` soft membership (row = component,
        column = cluster head; the hard one-hot at ``T = 0``), ``pi`` ``(G,)`` grid weights,
        ``grid_labels`` ``(G, K)`` hard labels on the grid, ``labels`` ``(K,)`` the hard labels at ``λ``.
    """
    dims = None if dims is None else tuple(int(i) for i in dims)
    g = jax.lax.stop_gradient(gm)
    delta = similarity_thresholds(g, dims)
    dist = centre_distances(g, dims)
    dtype = gm.means.dtype
    lam = jnp.asarray(lam, dtype)
    lam_sg = jax.lax.stop_gradient(lam)
    cluster = lambda l: gauss_cluster(g, l, triangular=triangular, subset_rule=subset_rule,  # noqa: E731
                                      range_scale=range_scale, delta=delta, dist=dist).labels
    labels = cluster(lam_sg)
    grid = jnp.asarray(grid, dtype)
    grid_labels = jax.lax.map(cluster, grid)
    T = jnp.asarray(temperature, dtype)
    pos = T > 0
    A_soft, pi = relaxed_membership(lam, grid, grid_labels, jnp.where(pos, T, 1.0))
    A_hard = onehot_membership(labels, gm.capacity, dtype)
    nearest = (jnp.arange(grid.shape[0]) == jnp.argmin(jnp.abs(grid - lam_sg))).astype(dtype)
    A = jnp.where(pos, A_soft, A_hard)
    pi = jnp.where(pos, pi, nearest)
    return A, pi, grid_labels, labels


def _pcm_validate(gm, rho, lam, alpha, temperature, lam_temperature, lambda_range, grid_size, merge, mode):
    _util.validate_mixture(gm)
    _util.validate_range(rho, "rho", 0.0, 1.0)
    _util.validate_nonneg(lam, "lam", allow_inf=False)
    _util.validate_nonneg(alpha, "alpha", allow_inf=False)
    _check_temperature(temperature)
    _check_temperature(lam_temperature, "lam_temperature")
    _check_mode(mode)
    if merge not in ("ci", "moment"):
        raise ValueError(f"merge: expected 'ci' or 'moment', got {merge!r}")
    if len(tuple(lambda_range)) != 2:
        raise ValueError(f"lambda_range: expected (low, high), got {lambda_range!r}")
    lo, hi = lambda_range
    if _util.is_concrete(lo, hi) and not float(lo) < float(hi):
        raise ValueError(f"lambda_range: need low < high, got {lambda_range!r}")
    _util.validate_count(grid_size, "grid_size", 2, 10_000)


def soft_pcm(
    gm: GaussianMixture,
    *,
    rho: ArrayLike = 0.9544,
    lam: ArrayLike = 2.0,
    alpha: ArrayLike = 0.001,
    temperature: ArrayLike = 0.0,
    lam_temperature: ArrayLike = 0.0,
    lambda_range: Sequence[ArrayLike] = (1.0, 3.0),
    grid_size: int = 9,
    max_components: int | None = None,
    range_scale: ArrayLike = 0.5,
    dims: Sequence[int] | None = None,
    merge: str = "ci",
    mode: str = "soft",
    capacity: int | None = None,
    key: PRNGKey | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """Prune-cluster-merge at a given ``λ`` with relaxed pruning and relaxed memberships.

    The hard counterpart is :func:`gmjax.reduction.pcm` with ``lam=λ`` (no search): censored pruning
    (seed 000 eqs 19–22, 41), Gauss clustering at ``σ* = λσ`` (eqs 23–28), covariance-intersection
    merge (eqs 38–39). Here the pruning uses :func:`censored_gates` (temperature ``T``, mass units)
    and the clustering :func:`soft_membership` over the grid of ``grid_size`` points on
    ``lambda_range`` (temperature ``T_λ``); each cluster is merged with the fractional memberships
    (:func:`gmjax.reduction._eise.merge_membership`), and the cost is the EISE of eq 29 on the soft
    clusters (the relaxation PCM's search minimises). With ``T = T_λ = 0`` (or ``mode="hard"``) the
    output, labels and cost equal ``pcm(gm, rho=ρ, lam=λ, ...)`` exactly; ``"straight_through"``
    returns the hard output with the relaxation's gradient.

    Soft clusters: every cluster that some grid clustering forms near ``λ`` is an output slot with
    its soft weight, so the relaxed output has more (light) components than the hard one; its
    expected size is ``info.aux["n_expected"] = Σ_g π_g Σ_c max_{m ∈ c_g} gate_m`` (a cluster exists
    when a member survives the pruning), which equals ``N'`` at ``T = 0``.

    Returns:
        ``(reduced, info)``: ``info.cost`` the (relaxed) EISE; ``info.aux`` holds ``lambda``,
        ``n_clusters`` (hard ``N'``), ``n_reference`` (survivors of the hard pruning), ``n_expected``
        and ``n_pruned_expected`` (``Σ`` of the pruning gates).
    """
    del key
    _pcm_validate(gm, rho, lam, alpha, temperature, lam_temperature, lambda_range, grid_size, merge, mode)
    if max_components is not None:
        max_components = _util.validate_count(max_components, "max_components", 1, 2**31 - 1)
    cap = _util.validate_capacity(capacity, gm)
    dims = None if dims is None else tuple(int(i) for i in dims)
    return _soft_pcm_core(gm, rho, lam, alpha, temperature, lam_temperature, tuple(lambda_range), range_scale,
                          grid_size=grid_size, max_components=max_components, dims=dims, merge=merge,
                          mode=mode, capacity=cap)


def _tree_select(pred, a, b):
    return jax.tree_util.tree_map(lambda x, y: jnp.where(pred, x, y), a, b)


@partial(jax.jit, static_argnames=("grid_size", "max_components", "dims", "merge", "mode", "capacity"))
def _soft_pcm_core(gm, rho, lam, alpha, temperature, lam_temperature, lambda_range, range_scale, *,
                   grid_size, max_components, dims, merge, mode, capacity):
    dtype = gm.means.dtype
    K = gm.capacity
    Kw = K if max_components is None else min(K, max_components)
    gates = censored_gates(gm, rho, temperature, max_components=max_components, mode=mode)
    # T or T_λ > 0 relaxes the reducer: negligible components are dropped (see gated_prune)
    relaxed = (jnp.asarray(temperature, dtype) > 0) | (jnp.asarray(lam_temperature, dtype) > 0)
    floor = jnp.where(relaxed, _negligible_floor(1.0, mode, dtype), 0.0)
    work, pinfo = gated_prune(gm, gates, Kw, floor)
    g_work = pinfo.aux["gates"]
    n_ref = jnp.sum(work.mask.astype(jnp.int32))
    lo, hi = (jnp.asarray(v, dtype) for v in lambda_range)
    grid = lo + (hi - lo) * jnp.linspace(0.0, 1.0, grid_size, dtype=dtype)
    lam = jnp.asarray(lam, dtype)
    if mode == "hard":
        labels = gauss_cluster(jax.lax.stop_gradient(work), jax.lax.stop_gradient(lam), dims=dims,
                               range_scale=range_scale).labels
    else:
        T_lam = jnp.asarray(lam_temperature, dtype)
        A, pi, grid_labels, labels = soft_membership(work, lam, grid, T_lam, dims=dims, range_scale=range_scale)

    # hard path: exactly pcm(lam=λ)'s merge and EISE
    merged_hard = merge_labels(work, labels, Kw, merge)
    value_hard, _, n_hard = hard_eise(work, labels, alpha=alpha, method=merge, regularizer="exp", ise_scale=0.5)
    n_hard_f = n_hard.astype(dtype)

    if mode == "hard":
        merged, value, n_exp = merged_hard, value_hard, n_hard_f
    else:
        # soft path: fractional merge (eqs 38–39 with weights A_mc w_m) and the relaxed EISE (eq 29)
        A_live = jnp.where(work.mask[:, None], A, 0.0)
        merged_soft = merge_membership(work, A_live, merge)
        onehots = jax.vmap(lambda lab: onehot_membership(lab, Kw, dtype))(grid_labels)  # (G, K, C)
        exists = jnp.max(onehots * g_work[None, :, None], axis=1)  # (G, C)
        n_soft = jnp.sum(pi[:, None] * exists)
        value_soft = eise(work, A_live, merged_soft, n_soft, n_ref, alpha=alpha, regularizer="exp",
                          ise_scale=0.5, clip=False)
        soft_on = T_lam > 0  # T_λ = 0: the hard clustering, merged and costed exactly as pcm does
        soft_f = _tree_select(soft_on, merged_soft, merged_hard)
        soft_n = jnp.where(soft_on, n_soft, n_hard_f)
        soft_v = jnp.where(soft_on, value_soft, value_hard)
        if mode == "soft":
            merged, value, n_exp = soft_f, soft_v, soft_n
        else:
            both = merged_hard.mask & soft_f.mask
            st = lambda h, s: jnp.where(  # noqa: E731
                both.reshape(both.shape + (1,) * (h.ndim - 1)), _straight_through(h, s), h)
            merged = GaussianMixture(st(merged_hard.weights, soft_f.weights), st(merged_hard.means, soft_f.means),
                                     st(merged_hard.covs, soft_f.covs), merged_hard.mask)
            value = _straight_through(value_hard, soft_v)
            n_exp = _straight_through(n_hard_f, soft_n)
    merged = sanitize(merged)
    to_work = pinfo.labels
    labels_in = jnp.where(to_work >= 0, labels[jnp.maximum(to_work, 0)], -1)
    out, labels_out, overflow, _ = _util.finalize(gm, merged, labels_in, capacity)
    aux = {"lambda": lam, "n_clusters": n_hard, "n_reference": n_ref, "n_expected": n_exp,
           "n_pruned_expected": pinfo.aux["n_expected"]}
    info = make_info(gm, out, labels_out, pruned_mass=pinfo.pruned_mass, overflow=overflow | pinfo.overflow,
                     cost=value, aux=aux)
    return out, info


@pytree_dataclass
class SoftPCM:
    """Reducer config for :func:`soft_pcm`: ``rho``, ``lam``, ``alpha`` and the temperatures are traced.

    ``SoftPCM(rho, lam, temperature=0, lam_temperature=0)`` is ``PCM(rho=rho, lam=lam)``; raise the
    temperatures to make the Monte Carlo loss differentiable in ``ρ`` and ``λ``.
    """

    rho: Any = 0.9544
    lam: Any = 2.0
    alpha: Any = 0.001
    temperature: Any = 0.0
    lam_temperature: Any = 0.0
    lambda_range: Any = (1.0, 3.0)
    range_scale: Any = 0.5
    grid_size: int = static_field(9)
    max_components: int | None = static_field(None)
    dims: tuple[int, ...] | None = static_field(None)
    merge: str = static_field("ci")
    mode: str = static_field("soft")
    capacity: int | None = static_field(None)

    def __call__(self, gm: GaussianMixture, *, key: PRNGKey | None = None):
        return soft_pcm(gm, rho=self.rho, lam=self.lam, alpha=self.alpha, temperature=self.temperature,
                        lam_temperature=self.lam_temperature, lambda_range=self.lambda_range,
                        grid_size=self.grid_size, max_components=self.max_components,
                        range_scale=self.range_scale, dims=self.dims, merge=self.merge, mode=self.mode,
                        capacity=self.capacity, key=key)


# ----------------------------------------------------------------------------- soft split trigger


def soft_split_gate(temperature: float = 0.0, *, mode: str = "soft",
                    relative: bool = False) -> Callable[[Array, Array], Array]:
    """A split trigger ``gate(ψ, ψ_th) -> [0, 1]`` for :class:`gmjax.filters.agsf.AGSFConfig`.

    Seed 001 splits a component when its degree of nonlinearity reaches the threshold (eqs 30–31,
    level ``n`` for ``ψ >= ψ_th r^(n-1)``); the adaptive filter moves the split components by
    ``l · gate`` along the principal axis, so a gate of 0 is no split. The relaxed gate is
    ``σ((ψ - ψ_th) / T)``; ``T = 0`` (or ``mode="hard"``) is the hard step ``[ψ >= ψ_th]``, exactly
    :func:`gmjax.filters.agsf.hard_gate`; ``"straight_through"`` splits exactly as the hard rule but
    passes the sigmoid's gradient to ``ψ_th``. With a soft gate every level triggers (the gate is
    never exactly 0) and a weakly triggered split moves its children by a small ``l · gate``.

    With ``relative=True`` the temperature is in units of the threshold, ``σ((ψ - ψ_th) / (T ψ_th))``
    = ``σ((ψ / ψ_th - 1) / T)``: one temperature then serves thresholds that span decades (the
    levels ``ψ_th r^(n-1)`` of eq 31, or a tuning run that moves ``ψ_th`` by orders of magnitude).

    Args:
        temperature: ``T >= 0`` in units of ``ψ`` (of ``ψ_th`` when ``relative``); a Python float,
            the gate is static config.
        mode: ``"hard"``, ``"soft"`` or ``"straight_through"``.
        relative: scale the temperature by the threshold.
    """
    _check_mode(mode)
    _check_temperature(temperature)

    def gate(psi: Array, threshold: Array) -> Array:
        psi = jnp.asarray(psi)
        thr = jnp.asarray(threshold, psi.dtype)
        T = jnp.asarray(temperature, psi.dtype) * (jnp.abs(thr) if relative else 1.0)
        return soft_step(psi - thr, T, mode=mode)

    return gate


# ----------------------------------------------------------------------------- differentiable studies


class TuneScores(NamedTuple):
    """Differentiable per-run, per-step scores (leading axes ``(N, T)``).

    Attributes:
        sq_error, position_sq_error: squared estimation errors (full state / position components).
        nees: normalised estimation error squared.
        cost: the reducer's cost (PCM's EISE; 0 where none).
        n_expected: expected live components after reduction (``info.reduction.aux["n_expected"]``
            where the reducer reports it, else the live count).
        flags: overflow / repaired covariance / degenerate update (bool).
    """

    sq_error: Array
    position_sq_error: Array
    nees: Array
    cost: Array
    n_expected: Array
    flags: Array


def _score(filter: Filter, scenario: Scenario, key: PRNGKey) -> TuneScores:
    from gmjax.montecarlo import filter_run

    r = filter_run(filter, scenario, key)
    truths, est, pos, infos = r.truths, r.estimates, r.position_dims, r.infos
    T, dtype = truths.shape[0], truths.dtype
    reduction = getattr(infos, "reduction", None)
    n_comp = getattr(infos, "n_components", None)
    n_exp = None if reduction is None else reduction.aux.get("n_expected") if isinstance(reduction.aux, dict) else None
    if n_exp is None:
        n_exp = jnp.ones(T, dtype) if n_comp is None else jnp.asarray(n_comp, dtype)
    return TuneScores(
        sq_error=metrics.squared_error(est, truths),
        position_sq_error=metrics.squared_error(est[:, pos], truths[:, pos]),
        nees=metrics.nees(est, r.covs, truths),
        cost=jnp.zeros(T, dtype) if reduction is None else jnp.asarray(reduction.cost, dtype),
        n_expected=jnp.asarray(n_exp, dtype),
        flags=r.flags,
    )


def study_scores(filter: Filter, scenario: Scenario, n_runs: int, key: PRNGKey) -> TuneScores:
    """Simulate, filter and score ``n_runs`` runs (``vmap``; traceable and differentiable).

    Run ``i`` uses ``jax.random.split(key, n_runs)[i]`` exactly as :func:`gmjax.monte_carlo` does, so
    the same key gives the same runs in both.
    """
    keys = jax.random.split(key, n_runs)
    return jax.vmap(lambda k: _score(filter, scenario, k))(keys)


def armse_loss(*, position: bool = True) -> Callable[[TuneScores], Array]:
    """ARMSE ``mean_t sqrt(mean_i e²_it)`` (seed 000 eq 44), of the position components by default."""

    def loss(scores: TuneScores) -> Array:
        sq = scores.position_sq_error if position else scores.sq_error
        return jnp.mean(jnp.sqrt(jnp.mean(sq, axis=0)))

    return loss


def anees_loss(target: float) -> Callable[[TuneScores], Array]:
    """``|ANEES - d|``: consistency (the ANEES of a consistent filter is the state dimension ``d``)."""

    def loss(scores: TuneScores) -> Array:
        return jnp.abs(jnp.mean(scores.nees) - target)

    return loss


def aeise_loss() -> Callable[[TuneScores], Array]:
    """AEISE: the reducer's EISE (seed 000 eq 29) averaged over runs and steps."""
    return lambda scores: jnp.mean(scores.cost)


def count_loss() -> Callable[[TuneScores], Array]:
    """Expected number of components after reduction, averaged over runs and steps (a cost)."""
    return lambda scores: jnp.mean(scores.n_expected)


def weighted_loss(*terms: tuple[float, Callable[[TuneScores], Array]]) -> Callable[[TuneScores], Array]:
    """``Σ_i c_i loss_i``; e.g. ``weighted_loss((1.0, armse_loss()), (0.01, count_loss()))``."""
    if not terms:
        raise ValueError("terms: need at least one (weight, loss) pair")
    for t in terms:
        if not (isinstance(t, tuple) and len(t) == 2 and callable(t[1])):
            raise ValueError(f"terms: expected (weight, loss) pairs, got {t!r}")

    def loss(scores: TuneScores) -> Array:
        return sum(float(c) * f(scores) for c, f in terms)

    return loss


# ----------------------------------------------------------------------------- reparameterisation


class Bounds(NamedTuple):
    """Valid range of one parameter: ``(low, high)``, either end ``None`` for unbounded.

    ``(lo, hi)`` maps ``u`` to ``lo + (hi - lo) σ(u)``; ``(lo, None)`` to ``lo + softplus(u)``;
    ``(None, hi)`` to ``hi - softplus(-u)``; ``(None, None)`` is the identity. With ``log=True``
    (``0 < lo < hi``) the interval is covered in log scale, ``exp(log lo + (log hi - log lo) σ(u))``,
    for thresholds that span decades.
    """

    low: float | None = None
    high: float | None = None
    log: bool = False

    def to_constrained(self, u: Array) -> Array:
        lo, hi = self.low, self.high
        if self.log:
            a, b = math.log(lo), math.log(hi)
            return jnp.exp(a + (b - a) * jax.nn.sigmoid(u))
        if lo is not None and hi is not None:
            return lo + (hi - lo) * jax.nn.sigmoid(u)
        if lo is not None:
            return lo + jax.nn.softplus(u)
        if hi is not None:
            return hi - jax.nn.softplus(-u)
        return u

    def to_unconstrained(self, x: float) -> float:
        lo, hi = self.low, self.high
        if self.log:
            p = (math.log(x) - math.log(lo)) / (math.log(hi) - math.log(lo))
            return math.log(p) - math.log1p(-p)
        if lo is not None and hi is not None:
            p = (x - lo) / (hi - lo)
            return math.log(p) - math.log1p(-p)
        if lo is not None:
            y = x - lo
            return y + math.log(-math.expm1(-y))
        if hi is not None:
            y = hi - x
            return -(y + math.log(-math.expm1(-y)))
        return x

    def contains(self, x: float) -> bool:
        return (self.low is None or x > self.low) and (self.high is None or x < self.high)


def _as_bounds(b: Any, name: str) -> Bounds:
    if b is None:
        return Bounds()
    if isinstance(b, Bounds):
        out = b
    elif isinstance(b, (tuple, list)) and len(b) == 2:
        out = Bounds(None if b[0] is None else float(b[0]), None if b[1] is None else float(b[1]))
    else:
        raise ValueError(f"bounds[{name!r}]: expected (low, high) or Bounds, got {b!r}")
    if out.low is not None and out.high is not None and not out.low < out.high:
        raise ValueError(f"bounds[{name!r}]: need low < high, got {b!r}")
    if out.log and (out.low is None or out.high is None or not out.low > 0):
        raise ValueError(f"bounds[{name!r}]: log scale needs 0 < low < high, got {b!r}")
    return out


class TuneHistory(NamedTuple):
    """What :func:`tune` did, step by step (NumPy arrays; ``steps`` rows).

    Attributes:
        loss: ``(steps,)`` loss at the parameters of that step (on that step's runs).
        params: name -> ``(steps,)`` the (constrained) parameters evaluated at each step.
        grads: name -> ``(steps,)`` d loss / d parameter (constrained) at each step.
        ok: ``(steps,)`` bool, the loss and gradient were finite (else the update was skipped).
        flag_rate: ``(steps,)`` fraction of filter steps flagged (overflow / repair / degenerate).
        step_s: ``(steps,)`` wall seconds of each step (the first includes compilation).
    """

    loss: np.ndarray
    params: dict[str, np.ndarray]
    grads: dict[str, np.ndarray]
    ok: np.ndarray
    flag_rate: np.ndarray
    step_s: np.ndarray


class TuneResult(NamedTuple):
    """Outcome of :func:`tune`: ``params`` (name -> float, after the last update) and ``history``."""

    params: dict[str, float]
    history: TuneHistory
    compile_s: float


def tune(
    filter_factory: Callable[[dict[str, Array]], Filter],
    scenario: Scenario,
    params0: Mapping[str, float],
    loss: Callable[[TuneScores], Array],
    optimizer: Any = None,
    n_runs: int = 16,
    steps: int = 20,
    *,
    key: PRNGKey,
    bounds: Mapping[str, Any] | None = None,
    resample: bool = True,
    ad: str = "forward",
    progress: bool = True,
) -> TuneResult:
    """Tune thresholds by gradient descent on a Monte Carlo loss.

    Each step simulates ``n_runs`` runs of ``scenario`` (:func:`study_scores`), filters them with
    ``filter_factory(params)`` and differentiates ``loss(scores)`` with respect to the parameters.
    The optimiser acts on unconstrained values ``u`` with ``params = bounds.to_constrained(u)``, so
    every threshold stays in its valid range. With ``resample`` each step draws fresh runs
    (stochastic gradient; step ``s`` uses ``fold_in(key, s)``), otherwise every step reuses the runs
    of ``key`` itself (common random numbers: a deterministic objective, the same runs as
    ``study_scores(..., key)`` and ``gmjax.monte_carlo(..., key)``). The whole step (simulation, filtering,
    loss, gradient) is one compiled function; changing the parameters never recompiles.

    Args:
        filter_factory: ``params -> Filter``; ``params`` is a dict of traced scalars (use relaxed
            reducers such as :class:`SoftPCM` or a :func:`soft_split_gate`, or the gradient is 0).
        scenario: the :class:`~gmjax.models.Scenario` to simulate.
        params0: name -> initial value (inside its bounds).
        loss: ``TuneScores -> ()``, e.g. :func:`armse_loss` or :func:`weighted_loss`.
        optimizer: an optax ``GradientTransformation`` (default ``optax.adam(0.05)``, in
            unconstrained units).
        n_runs: Monte Carlo runs per step.
        steps: optimiser steps.
        key: PRNG key (keyword-only).
        bounds: name -> ``(low, high)`` / :class:`Bounds` (default unbounded).
        resample: fresh runs every step (default) or common random numbers.
        ad: ``"forward"`` (``jax.jacfwd``: cheap for a few parameters, memory independent of the
            horizon) or ``"reverse"`` (``jax.grad``).
        progress: print one line per step to stderr.

    Returns:
        A :class:`TuneResult`; ``plot_history(result.history)`` plots it.

    Raises:
        ValueError: bad arguments (naming them), or an initial value outside its bounds.
    """
    import optax

    if not callable(filter_factory):
        raise ValueError("filter_factory: expected a callable params -> Filter")
    if not callable(loss):
        raise ValueError("loss: expected a callable TuneScores -> scalar")
    if not isinstance(params0, Mapping) or not params0:
        raise ValueError(f"params0: expected a non-empty dict name -> value, got {params0!r}")
    for name, arg in (("n_runs", n_runs), ("steps", steps)):
        if isinstance(arg, bool) or not isinstance(arg, int) or arg < 1:
            raise ValueError(f"{name}: must be a positive int, got {arg!r}")
    if ad not in ("forward", "reverse"):
        raise ValueError(f"ad: expected 'forward' or 'reverse', got {ad!r}")
    bounds = dict(bounds or {})
    unknown = sorted(set(bounds) - set(params0))
    if unknown:
        raise ValueError(f"bounds: names {unknown} are not in params0")
    names = sorted(params0)
    bnds = {n: _as_bounds(bounds.get(n), n) for n in names}
    for n in names:
        v = float(params0[n])
        if not math.isfinite(v) or not bnds[n].contains(v):
            raise ValueError(f"params0[{n!r}]: {v} is not strictly inside its bounds {tuple(bnds[n])}")
    optimizer = optax.adam(0.05) if optimizer is None else optimizer
    dtype = jnp.zeros(()).dtype
    u = jnp.asarray([bnds[n].to_unconstrained(float(params0[n])) for n in names], dtype)

    def constrained(u_vec):
        return {n: bnds[n].to_constrained(u_vec[i]) for i, n in enumerate(names)}

    def objective(u_vec, k):
        scores = study_scores(filter_factory(constrained(u_vec)), scenario, n_runs, k)
        return loss(scores), jnp.mean(scores.flags.astype(dtype))

    if ad == "forward":
        def value_and_grad(u_vec, k):
            def f(v):
                val, flag = objective(v, k)
                return val, (val, flag)
            g, (val, flag) = jax.jacfwd(f, has_aux=True)(u_vec)
            return val, flag, g
    else:
        def value_and_grad(u_vec, k):
            (val, flag), g = jax.value_and_grad(objective, has_aux=True)(u_vec, k)
            return val, flag, g

    def step_fn(u_vec, opt_state, k):
        val, flag, g_u = value_and_grad(u_vec, k)
        ok = jnp.isfinite(val) & jnp.all(jnp.isfinite(g_u))
        g_safe = jnp.where(ok, g_u, 0.0)
        updates, new_state = optimizer.update(g_safe, opt_state, u_vec)
        new_u = jnp.where(ok, optax.apply_updates(u_vec, updates), u_vec)
        new_state = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new_state, opt_state)
        # chain rule back to the constrained parameters: dL/dθ = (dL/du) / (dθ/du)
        jac = jnp.diagonal(jax.jacfwd(lambda v: jnp.stack([constrained(v)[n] for n in names]))(u_vec))
        g_theta = g_u / jac
        return new_u, new_state, val, flag, g_theta, ok

    opt_state = optimizer.init(u)
    step_jit = jax.jit(step_fn)
    t0 = time.perf_counter()
    key0 = jax.random.fold_in(key, 0) if resample else key
    compiled = step_jit.lower(u, opt_state, key0).compile()
    compile_s = time.perf_counter() - t0

    losses, oks, flags, times = [], [], [], []
    p_hist = {n: [] for n in names}
    g_hist = {n: [] for n in names}
    for s in range(steps):
        k = jax.random.fold_in(key, s) if resample else key0
        theta = {n: float(v) for n, v in constrained(u).items()}
        t1 = time.perf_counter()
        u, opt_state, val, flag, g_theta, ok = compiled(u, opt_state, k)
        val = float(val)
        times.append(time.perf_counter() - t1)
        losses.append(val)
        oks.append(bool(ok))
        flags.append(float(flag))
        for i, n in enumerate(names):
            p_hist[n].append(theta[n])
            g_hist[n].append(float(g_theta[i]))
        if progress:
            ps = " ".join(f"{n}={theta[n]:.4g}" for n in names)
            sys.stderr.write(f"tune step {s + 1}/{steps}: loss {val:.5g}  {ps}"
                             f"{'' if ok else '  (non-finite: update skipped)'}  {times[-1]:.1f} s\n")
            sys.stderr.flush()
    history = TuneHistory(
        loss=np.asarray(losses), params={n: np.asarray(v) for n, v in p_hist.items()},
        grads={n: np.asarray(v) for n, v in g_hist.items()}, ok=np.asarray(oks),
        flag_rate=np.asarray(flags), step_s=np.asarray(times),
    )
    final = {n: float(v) for n, v in constrained(u).items()}
    return TuneResult(final, history, compile_s)


def plot_history(history: TuneHistory, path: str | None = None, *, title: str | None = None):
    """Plot the loss and every parameter against the step (matplotlib, imported lazily).

    Args:
        history: a :class:`TuneHistory`.
        path: save the figure there (PNG) when given.
        title: figure title.

    Returns:
        The matplotlib ``Figure``.
    """
    import matplotlib.pyplot as plt

    names = list(history.params)
    fig, axes = plt.subplots(1, 1 + len(names), figsize=(4 * (1 + len(names)), 3.2))
    axes = np.atleast_1d(axes)
    steps = np.arange(1, len(history.loss) + 1)
    axes[0].plot(steps, history.loss, marker=".")
    axes[0].set(xlabel="step", ylabel="loss", title="loss")
    for ax, n in zip(axes[1:], names):
        ax.plot(steps, history.params[n], marker=".")
        ax.set(xlabel="step", ylabel=n, title=n)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=90)
    return fig
