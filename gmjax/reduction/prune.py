"""Pruning: weight threshold, number-limited (top-N) and j-th order statistic censored pruning.

Every pruner keeps whole components, scales the survivors' weights so that the total weight is
unchanged (for a normalised input: eq 41 of seed 000), and reports the removed weight in
``ReductionInfo.pruned_mass``. Survivors are stored heaviest first.

The threshold and censored pruners carry a relaxation (DESIGN §3): a static ``mode``
(``"hard"``, the default and the rule above; ``"soft"``; ``"straight_through"``) and a traced
``temperature`` ``T``. In the relaxed modes every weight is scaled by a sigmoid gate of its
decision margin (:func:`gmjax.reduction.relax.threshold_gates`,
:func:`gmjax.reduction.relax.censored_gates`) and the survivors are renormalised
(:func:`gmjax.reduction.relax.gated_prune`), so the output is differentiable in the threshold;
``mode="soft"`` with ``T = 0`` is the hard rule exactly, and ``"straight_through"`` returns the hard
output with the relaxation's gradient.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp

from gmjax import _validate
from gmjax._pytree import pytree_dataclass, static_field
from gmjax.mixture import GaussianMixture, descending_ranks, heaviest_slots, pad, sanitize
from gmjax.reduction import _util
from gmjax.reduction.base import ReductionInfo, Stateless, calls, make_info
from gmjax.reduction.relax import (
    censored_gates,
    gated_prune,
    negligible_floor,
    select_kept,
    threshold_gates,
    validate_mode,
    validate_temperature,
)

__all__ = [
    "prune_threshold",
    "prune_top",
    "prune_censored",
    "PruneThreshold",
    "PruneTop",
    "PruneCensored",
]


@partial(jax.jit, static_argnames=("capacity",))
def _keep(gm: GaussianMixture, keep: jax.Array, capacity: int):
    """Keep the slots in ``keep`` (heaviest first, at most ``capacity``), renormalise, build info.

    If nothing survives, the heaviest live component is kept (a mixture is never emptied).
    """
    w = jnp.where(gm.mask, gm.weights, 0.0)
    total = jnp.sum(w)
    keep = keep & gm.mask
    heaviest = jnp.argmax(jnp.where(gm.mask, w, -jnp.inf))
    keep = jnp.where(jnp.any(keep), keep, jnp.arange(gm.capacity) == heaviest)
    n_keep = jnp.sum(keep.astype(jnp.int32))
    idx, sel_valid, labels = select_kept(gm, keep, w, capacity)
    out = jax.tree_util.tree_map(lambda a: a[idx], gm)
    out = out._replace(mask=sel_valid)
    kept_mass = jnp.sum(jnp.where(sel_valid, out.weights, 0.0))
    scale = jnp.where(kept_mass > 0, total / jnp.where(kept_mass > 0, kept_mass, 1.0), 1.0)
    out = sanitize(out._replace(weights=out.weights * scale))
    overflow = n_keep > capacity
    return out, make_info(
        gm, out, labels, pruned_mass=total - kept_mass, overflow=overflow, aux={"scale": scale}
    )


def prune_threshold(
    gm: GaussianMixture,
    threshold: Any,
    *,
    temperature: Any = 0.0,
    mode: str = "hard",
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """Drop components whose weight is below ``threshold`` and renormalise.

    Weights are compared as stored (``w_k < threshold`` is dropped); the survivors are scaled so the
    total weight is unchanged. If every component is below the threshold the heaviest is kept.

    Relaxed modes: the gate of component ``k`` is ``σ((w_k - threshold) / T)``
    (:func:`gmjax.reduction.relax.threshold_gates`), its weight becomes ``g_k w_k`` and the
    survivors are renormalised (:func:`gmjax.reduction.relax.gated_prune`).

    Args:
        gm: input mixture, capacity ``K``.
        threshold: ``()`` non-negative, may be traced (in ``"hard"`` mode its gradient is 0 almost
            everywhere).
        temperature: ``()`` ``T >= 0`` of the relaxed modes, in weight units (traced; unused when
            ``mode="hard"``).
        mode: static ``"hard"`` (default), ``"soft"`` (``T = 0``: identical to ``"hard"``) or
            ``"straight_through"`` (hard value, the soft gradient).
        capacity: static output capacity (default ``K``); on overflow the heaviest are kept.
        key: unused (Reducer protocol).

    Returns:
        ``(pruned mixture, info)``; ``info.pruned_mass`` is the removed weight (before renormalising).
        In the relaxed modes ``info.aux`` also holds ``gates`` (the output slots' gates) and
        ``n_expected`` (``Σ_k g_k``, the expected number of survivors).
    """
    del key
    (threshold, temperature), bad = _util.replace_nans((threshold, 1e-5), (temperature, 0.0))
    _validate.validate_mixture(gm)
    _validate.validate_nonneg(threshold, "threshold")
    validate_temperature(temperature)
    validate_mode(mode)
    cap = _validate.validate_capacity(capacity, gm)
    if mode != "hard":
        gates = threshold_gates(gm, threshold, temperature, mode=mode)
        out = gated_prune(gm, gates, cap, negligible_floor(temperature, mode, gm.weights.dtype))
    else:
        threshold = jnp.asarray(threshold, gm.weights.dtype)
        out = _keep(gm, gm.mask & (gm.weights >= threshold), cap)
    return _util.unchanged_if_nan(bad, gm, out)


def prune_top(
    gm: GaussianMixture,
    num_out: int,
    *,
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """Number-limited pruning: keep the ``num_out`` heaviest components and renormalise (NL-GMR).

    This is the NL-GMR baseline of seed 000 (its ref. [12]). Ties keep the lower slot index.

    Args:
        gm: input mixture, capacity ``K``.
        num_out: static, ``1 <= num_out <= K``.
        capacity: static output capacity, ``>= num_out`` (default ``K``).
        key: unused.
    """
    del key
    _validate.validate_mixture(gm)
    num_out = _validate.validate_count(num_out, "num_out", 1, gm.capacity)
    cap = _validate.validate_capacity(capacity, gm, minimum=num_out)
    return _prune_top(gm, num_out, cap)


@partial(jax.jit, static_argnames=("num_out", "cap"))
def _prune_top(gm, num_out, cap):
    """One ``top_k`` picks the survivors already in output order (heaviest first, ties: lower slot):
    no keep mask, no second selection. Padded slots are never picked ahead of a live one."""
    w = jnp.where(gm.mask, gm.weights, 0.0)
    total = jnp.sum(w)
    idx, kept = heaviest_slots(gm.weights, gm.mask, num_out)
    out = jax.tree_util.tree_map(lambda a: a[idx], gm)._replace(mask=kept)
    kept_mass = jnp.sum(jnp.where(kept, out.weights, 0.0))
    scale = jnp.where(kept_mass > 0, total / jnp.where(kept_mass > 0, kept_mass, 1.0), 1.0)
    out = sanitize(out._replace(weights=out.weights * scale))
    if cap > num_out:
        out = pad(out, cap)
    slot = jnp.where(kept, jnp.arange(num_out, dtype=jnp.int32), -1)
    labels = jnp.full(gm.capacity, -1, jnp.int32).at[idx].set(slot)
    return out, make_info(gm, out, labels, pruned_mass=total - kept_mass, aux={"scale": scale})


def censored_count(gm: GaussianMixture, rho: Any, max_components: int | None = None) -> jax.Array:
    """Number of survivors ``N`` of the j-th order statistic pruning (seed 000 eqs 19–22).

    With the live weights sorted ascending (eq 19), ``gamma_n`` is the share of the total carried by
    the ``I - n + 1`` largest (eq 20), ``n_max`` is the largest ``n`` with ``gamma_n >= rho``
    (eq 21) and ``N = min(I - n_max + 1, N_u)`` (eq 22). Equivalently ``I - n_max + 1`` is the
    smallest ``m`` whose ``m`` largest weights hold at least ``rho`` of the total (``gamma_1 = 1``
    so ``N >= 1`` for ``rho <= 1``).
    """
    return _censored_count(gm, _heaviest_first(gm)[0], rho, max_components)


def _heaviest_first(gm: GaussianMixture) -> tuple[jax.Array, jax.Array]:
    """``(order, rank)``, ``(K,)`` int32: the slots by descending weight (ties: the lower slot
    first; padded slots last), and each slot's place in that order."""
    rank = descending_ranks(jnp.where(gm.mask, gm.weights, -jnp.inf))
    return jnp.zeros(gm.capacity, jnp.int32).at[rank].set(jnp.arange(gm.capacity, dtype=jnp.int32)), rank


def _censored_count(gm: GaussianMixture, order: jax.Array, rho: Any, max_components: int | None) -> jax.Array:
    """:func:`censored_count` with the descending ``order`` of :func:`_heaviest_first`."""
    w = jnp.where(gm.mask, gm.weights, 0.0)
    total = jnp.sum(w)
    desc = w[order]  # descending, padded zeros last
    csum = jnp.cumsum(desc)
    I = jnp.sum(gm.mask.astype(jnp.int32))
    live_rank = jnp.arange(gm.capacity) < I
    m_star = 1 + jnp.sum((live_rank & (csum < rho * total)).astype(jnp.int32))
    N = jnp.minimum(m_star, I)
    if max_components is not None:
        N = jnp.minimum(N, max_components)
    return N


def prune_censored(
    gm: GaussianMixture,
    rho: Any = 0.9544,
    max_components: int | None = None,
    *,
    temperature: Any = 0.0,
    mode: str = "hard",
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """Adaptive weight-censored pruning by the j-th order statistic (seed 000 eqs 19–22, 41).

    Keeps the ``N`` largest components, ``N = min(I - n_max + 1, N_u)`` (eqs 19–22, see
    :func:`censored_count`), and resets their weights by eq 41. Eq 41 as printed divides by
    ``1 - sum_{m=1}^{I-N+1} w^(m)``; keeping the ``N`` largest removes the ``I - N`` smallest, so
    the upper limit ``I - N + 1`` would also subtract the smallest kept weight and leave weights
    summing to more than 1. We read it as the removed mass (limit ``I - N``), i.e. the kept weights
    are scaled to the input's total weight (1 for a normalised input).

    Relaxed modes: the component of rank ``r`` (descending weights) gets the gate
    ``σ((ρ W - c_r) / T)``, ``c_r`` the mass of the ``r`` heavier components
    (:func:`gmjax.reduction.relax.censored_gates`; rank 0 always 1, ranks ``>= N_u`` always 0); its
    weight becomes ``g_k w_k`` and the survivors are renormalised (eq 41,
    :func:`gmjax.reduction.relax.gated_prune`).

    Args:
        gm: input mixture, capacity ``K``.
        rho: censoring threshold in ``[0, 1]`` (default 0.9544, the 2-sigma rule); may be traced.
        max_components: static cap ``N_u`` (default: no cap beyond the output capacity).
        temperature: ``()`` ``T >= 0`` of the relaxed modes, in units of probability mass (traced;
            unused when ``mode="hard"``).
        mode: static ``"hard"`` (default), ``"soft"`` (``T = 0``: identical to ``"hard"``) or
            ``"straight_through"``.
        capacity: static output capacity (default ``K``).
        key: unused.

    Returns:
        ``(pruned mixture, info)``; ``info.aux`` holds ``n_keep`` (``N``) in ``"hard"`` mode, and
        ``gates`` and ``n_expected`` (``Σ_k g_k``) in the relaxed modes.
    """
    del key
    (rho, temperature), bad = _util.replace_nans((rho, 0.9544), (temperature, 0.0))
    _validate.validate_mixture(gm)
    _validate.validate_range(rho, "rho", 0.0, 1.0)
    validate_temperature(temperature)
    validate_mode(mode)
    if max_components is not None:
        max_components = _validate.validate_count(max_components, "max_components", 1, 2**31 - 1)
    cap = _validate.validate_capacity(capacity, gm)
    if mode != "hard":
        gates = censored_gates(gm, rho, temperature, max_components=max_components, mode=mode)
        out = gated_prune(gm, gates, cap, negligible_floor(temperature, mode, gm.weights.dtype))
    else:
        out = _prune_censored(gm, jnp.asarray(rho, gm.weights.dtype), max_components, cap)
    return _util.unchanged_if_nan(bad, gm, out)


@partial(jax.jit, static_argnames=("max_components", "cap"))
def _prune_censored(gm, rho, max_components, cap):
    order, rank = _heaviest_first(gm)
    N = _censored_count(gm, order, rho, max_components)
    out, info = _keep(gm, gm.mask & (rank < N), cap)
    return out, info._replace(aux={**info.aux, "n_keep": N})


# ----------------------------------------------------------------------------- Reducer configs


@pytree_dataclass
class PruneThreshold(Stateless):
    """Reducer config for :func:`prune_threshold`.

    ``threshold`` and ``temperature`` (the relaxation's ``T``, weight units) are dynamic; ``mode``
    (``"hard"`` default, ``"soft"``, ``"straight_through"``) and ``capacity`` are static.
    """

    threshold: Any = 1e-5
    capacity: int | None = static_field(None)
    temperature: Any = 0.0
    mode: str = static_field("hard")

    __call__ = calls(prune_threshold)


@pytree_dataclass
class PruneTop(Stateless):
    """Reducer config for :func:`prune_top`.

    ``heaviest_first``: the output's live slots come first, heaviest first, so a filter fits it to a
    smaller capacity by slicing (:func:`gmjax.filters.gsf.fit_capacity`).
    """

    heaviest_first = True

    num_out: int = static_field(10)
    capacity: int | None = static_field(None)

    __call__ = calls(prune_top)


@pytree_dataclass
class PruneCensored(Stateless):
    """Reducer config for :func:`prune_censored`.

    ``rho`` and ``temperature`` (the relaxation's ``T``, probability-mass units) are dynamic;
    ``max_components``, ``capacity`` and ``mode`` (``"hard"`` default, ``"soft"``,
    ``"straight_through"``) are static.
    """

    rho: Any = 0.9544
    max_components: int | None = static_field(None)
    capacity: int | None = static_field(None)
    temperature: Any = 0.0
    mode: str = static_field("hard")

    __call__ = calls(prune_censored)
