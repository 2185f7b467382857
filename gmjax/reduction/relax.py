"""Relaxations of the thresholded decisions of reduction (and splitting): soft gates and memberships.

Every reduction threshold of the papers (``ρ`` of the censored pruning, seed 000 eqs 19–22; ``λ`` of
the similarity clustering, eqs 23–28; a weight threshold; the split threshold ``ψ_th`` of seed 001
eq 31) makes a *hard* decision, so a Monte Carlo loss is piecewise constant in it and its gradient
is 0 almost everywhere. The reducers therefore carry a relaxation (DESIGN §3): a static ``mode``
and a traced temperature ``T`` (see :class:`~gmjax.reduction.PruneThreshold`,
:class:`~gmjax.reduction.PruneCensored`, :class:`~gmjax.reduction.PCM`). This module holds the
primitives they share:

* :func:`soft_step` — the relaxed Heaviside step ``σ(x / T)``; ``T = 0`` is the hard step exactly.
* :func:`threshold_gates`, :func:`censored_gates` — soft pruning gates; :func:`gated_prune` scales
  every weight by its gate and renormalises the survivors (with 0/1 gates: the hard pruning).
* :func:`soft_membership` — soft similarity memberships ``A(λ) = Σ_g π_g(λ) A_g`` over a fixed grid
  of ``λ``, the relaxation PCM's Newton search already uses
  (:func:`gmjax.reduction.eise.relaxed_membership`).
* :func:`soft_split_gate` — the soft split trigger for :class:`gmjax.filters.agsf.AGSFConfig`
  (``split_gate=``): a ``(ψ, ψ_th) -> gate`` function whose gate scales the split displacement.

Modes (static, :data:`MODES`): ``"hard"`` (the original decision), ``"soft"`` (the relaxation;
``T = 0`` reproduces ``"hard"`` exactly) and ``"straight_through"`` (hard forward pass, the
relaxation's gradient: ``hard + (soft - stop_gradient(soft))``, whose value is exactly ``hard``).
"""

from __future__ import annotations

from functools import partial
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp

from gmjax import _validate
from gmjax._types import Array, ArrayLike, DTypeLike
from gmjax.mixture import GaussianMixture, heaviest_slots, sanitize
from gmjax.reduction.base import ReductionInfo, make_info
from gmjax.reduction.clustering import centre_distances, gauss_cluster, similarity_thresholds
from gmjax.reduction.eise import onehot_membership, relaxed_membership

__all__ = [
    "MODES",
    "validate_mode",
    "validate_temperature",
    "straight_through",
    "soft_step",
    "threshold_gates",
    "censored_gates",
    "negligible_floor",
    "select_kept",
    "gated_prune",
    "soft_membership",
    "soft_split_gate",
]

MODES = ("hard", "soft", "straight_through")


def validate_mode(mode: Any, name: str = "mode") -> str:
    """``mode`` if it is one of :data:`MODES`, else a ``ValueError`` naming ``name``."""
    if not isinstance(mode, str) or mode not in MODES:
        raise ValueError(f"{name}: expected one of {MODES}, got {mode!r}")
    return mode


def validate_temperature(temperature: Any, name: str = "temperature") -> None:
    """``ValueError`` when a concrete temperature is negative, NaN or infinite (no-op on tracers)."""
    _validate.validate_nonneg(temperature, name, allow_inf=False)


def straight_through(hard: Array, soft: Array) -> Array:
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

    Returns:
        Gates of the shape of ``x`` in ``[0, 1]`` (floating dtype of ``x``, or the default float).
    """
    validate_mode(mode)
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
    return straight_through(hard, soft)


# ----------------------------------------------------------------------------- pruning gates


def threshold_gates(
    gm: GaussianMixture, threshold: ArrayLike, temperature: ArrayLike, *, mode: str = "soft"
) -> Array:
    """``(K,)`` gates of weight-threshold pruning: ``σ((w_k - threshold) / T)``, 0 on padding.

    The hard gate ``[w_k >= threshold]`` is :func:`gmjax.reduction.prune_threshold`'s rule; ``T`` is
    in weight units.
    """
    w = jnp.where(gm.mask, gm.weights, 0.0)
    g = soft_step(w - jnp.asarray(threshold, w.dtype), temperature, mode=mode)
    return jnp.where(gm.mask, g, 0.0)


def censored_gates(
    gm: GaussianMixture,
    rho: ArrayLike,
    temperature: ArrayLike,
    *,
    max_components: int | None = None,
    mode: str = "soft",
) -> Array:
    """``(K,)`` gates of the j-th order statistic censored pruning (seed 000 eqs 19–22).

    With the live weights in descending order, the component of rank ``r`` (0-based) survives the
    hard rule iff ``c_r < ρ W`` where ``c_r`` is the mass of the ``r`` heavier components and ``W``
    the total: this is eqs 20–22 (``N`` = the smallest count whose largest weights hold ``ρ`` of the
    total; see :func:`gmjax.reduction.censored_count`). The relaxed gate is
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


def negligible_floor(temperature: ArrayLike, mode: str, dtype: DTypeLike) -> Array:
    """``eps²`` of ``dtype`` for a relaxed (``"soft"``, ``T > 0``) gate, else 0 (see :func:`gated_prune`)."""
    eps2 = jnp.asarray(jnp.finfo(dtype).eps ** 2, dtype)
    if mode != "soft":
        return jnp.zeros((), dtype)
    return jnp.where(jnp.asarray(temperature, dtype) > 0, eps2, 0.0)


# ----------------------------------------------------------------------------- gated pruning


def select_kept(gm: GaussianMixture, keep: Array, w: Array, capacity: int) -> tuple[Array, Array, Array]:
    """Order the kept slots by weight, heaviest first (ties: lower slot index), in ``capacity`` slots.

    Shared by the hard pruners of :mod:`gmjax.reduction` and :func:`gated_prune`.

    Returns:
        ``idx`` ``(capacity,)`` input slot of each output slot, ``valid`` ``(capacity,)`` whether it
        holds a kept slot (at most ``capacity`` of them survive), and ``labels`` ``(K,)`` the output
        slot of every input slot (``-1`` where it was dropped or is padding).
    """
    K = gm.capacity
    idx, valid = heaviest_slots(w, keep, capacity)
    pos = jnp.full(K, -1, jnp.int32).at[idx].max(jnp.where(valid, jnp.arange(capacity, dtype=jnp.int32), -1))
    return idx, valid, jnp.where(gm.mask, pos, -1)


@partial(jax.jit, static_argnames=("capacity",))
def gated_prune(
    gm: GaussianMixture, gates: Array, capacity: int, floor: ArrayLike = 0.0
) -> tuple[GaussianMixture, ReductionInfo]:
    """Scale every weight by its gate, drop gate-0 slots, keep the heaviest ``capacity``, renormalise.

    With 0/1 gates this is exactly the hard pruning of :func:`gmjax.reduction.prune_threshold` /
    :func:`gmjax.reduction.prune_censored` (same slot order: survivors heaviest first, ties by slot;
    survivors scaled to the input's total weight, seed 000 eq 41; if nothing survives the heaviest
    component is kept). With soft gates a component's weight becomes ``g_k w_k W / Σ_j g_j w_j``:
    every weight is a smooth function of the gates.

    ``floor``: slots whose gated weight ``g_k w_k`` is below ``floor · W`` are dropped as well. The
    relaxed reducers pass ``eps²`` of the dtype when ``T > 0`` (0 otherwise, so ``T = 0`` stays
    exact; :func:`negligible_floor`): such a component is below rounding in every output, but a soft
    gate would keep it live, and merging it alone (weight ``~1e-160``) squares its weight in the
    derivative of ``ω / W``, which underflows to a non-finite gradient.

    Args:
        gm: input mixture, capacity ``K``.
        gates: ``(K,)`` gates in ``[0, 1]`` (0 on padding).
        capacity: static output capacity.
        floor: ``()`` relative weight floor (see above).

    Returns:
        ``(pruned, info)``; ``info.aux`` holds ``scale``, ``gates`` (``(capacity,)``, the output
        slots' gates) and ``n_expected`` (``Σ_k g_k``, the expected number of survivors).
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
    info = make_info(
        gm,
        out,
        labels,
        pruned_mass=total - kept_mass,
        overflow=n_keep > capacity,
        aux={"scale": scale, "gates": g_out, "n_expected": jnp.sum(gates)},
    )
    return out, info


# ----------------------------------------------------------------------------- soft memberships


def soft_membership(
    gm: GaussianMixture,
    lam: ArrayLike,
    grid: Array,
    temperature: ArrayLike,
    *,
    dims: Sequence[int] | None = None,
    range_scale: ArrayLike = 0.5,
    triangular: bool = False,
    subset_rule: str = "split",
) -> tuple[Array, Array, Array, Array]:
    """Soft similarity memberships at ``λ``, shared with PCM's confidence search.

    The hard clustering (seed 000 eqs 23–28, :func:`gmjax.reduction.gauss_cluster`) is piecewise
    constant in ``λ``. As in PCM's Newton search (:mod:`gmjax.reduction.eise`), the relaxation is the
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
    cluster = lambda l: (  # noqa: E731
        gauss_cluster(
            g,
            l,
            triangular=triangular,
            subset_rule=subset_rule,
            range_scale=range_scale,
            delta=delta,
            dist=dist,
        ).labels
    )
    labels = cluster(lam_sg)
    grid = jnp.asarray(grid, dtype)
    grid_labels = cluster(grid)  # (G, K), one overlap sweep
    T = jnp.asarray(temperature, dtype)
    pos = T > 0
    A_soft, pi = relaxed_membership(lam, grid, grid_labels, jnp.where(pos, T, 1.0))
    A_hard = onehot_membership(labels, gm.capacity, dtype)
    nearest = (jnp.arange(grid.shape[0]) == jnp.argmin(jnp.abs(grid - lam_sg))).astype(dtype)
    A = jnp.where(pos, A_soft, A_hard)
    pi = jnp.where(pos, pi, nearest)
    return A, pi, grid_labels, labels


# ----------------------------------------------------------------------------- soft split trigger


def soft_split_gate(
    temperature: float = 0.0, *, mode: str = "soft", relative: bool = False
) -> Callable[[Array, Array], Array]:
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

    Also importable as ``gmjax.tune.soft_split_gate``.

    Args:
        temperature: ``T >= 0`` in units of ``ψ`` (of ``ψ_th`` when ``relative``); a Python float,
            the gate is static config.
        mode: ``"hard"``, ``"soft"`` or ``"straight_through"``.
        relative: scale the temperature by the threshold.

    Raises:
        ValueError: a bad ``mode`` or a negative / non-finite ``temperature``.
    """
    validate_mode(mode)
    validate_temperature(temperature)

    def gate(psi: Array, threshold: Array) -> Array:
        psi = jnp.asarray(psi)
        thr = jnp.asarray(threshold, psi.dtype)
        T = jnp.asarray(temperature, psi.dtype) * (jnp.abs(thr) if relative else 1.0)
        return soft_step(psi - thr, T, mode=mode)

    return gate
