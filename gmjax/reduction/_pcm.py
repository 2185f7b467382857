"""Prune-cluster-merge mixture reduction, PCM-GMR (seed 000, Table 1 steps 2–7).

1. *Weight-censored pruning* by the j-th order statistic (eqs 19–22, ``ρ = 0.9544``, cap ``N_u``)
   with the survivors' weights reset by eq 41 (:func:`gmjax.reduction._prune.prune_censored`).
2. *Gauss clustering* by the distribution-similarity criterion at confidence range ``σ* = λσ``
   (eqs 23–28, :mod:`gmjax.reduction._clustering`).
3. *Covariance-intersection merging* of every cluster with the normalised weights (eqs 38–39, 41).
4. *Confidence-range search*: ``λ`` minimising the EISE ``½ Σ_c ∫ (f_c - q_c)² + α e^{N'/N}``
   (eqs 29–35) over the scope ``[1, 3]`` (§IV-A), by a grid and Newton–Raphson steps on a smooth
   relaxation (:mod:`gmjax.reduction._eise`; the hard EISE is piecewise constant in ``λ``, so Newton
   needs the relaxation), falling back to the grid's best.

Everything is a fixed-capacity array program: ``jit``, ``vmap`` over mixtures, and ``lax.scan`` in a
filter work, and ``λ``, ``ρ``, ``α`` and the temperature are traced config fields.
"""

from __future__ import annotations

from functools import partial
from typing import Any, Sequence

import jax
import jax.numpy as jnp

from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array, ArrayLike
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction._base import ReductionInfo, make_info
from gmjax.reduction._clustering import gauss_cluster
from gmjax.reduction._eise import SearchResult, hard_eise, search_confidence
from gmjax.reduction._merge import merge_labels
from gmjax.reduction._prune import prune_censored

__all__ = ["pcm", "PCM", "search_aux", "validate_search_args"]


def validate_search_args(
    *,
    lam: Any,
    lambda_range: Sequence[Any],
    alpha: Any,
    temperature: Any,
    tol: Any,
    range_scale: Any,
    grid_size: int,
    newton_steps: int,
    dims: Sequence[int] | None,
    dim: int,
) -> None:
    """Eager ``ValueError`` checks shared by :func:`pcm` and ``gmrcm`` (no-op on tracers)."""
    if len(tuple(lambda_range)) != 2:
        raise ValueError(f"lambda_range: expected (low, high), got {lambda_range!r}")
    lo, hi = lambda_range
    _util.validate_nonneg(lo, "lambda_range")
    _util.validate_nonneg(hi, "lambda_range")
    if _util.is_concrete(lo, hi) and not float(lo) < float(hi):
        raise ValueError(f"lambda_range: need low < high, got {lambda_range!r}")
    if lam is not None:
        _util.validate_nonneg(lam, "lam", allow_inf=False)
    _util.validate_nonneg(alpha, "alpha", allow_inf=False)
    _util.validate_nonneg(tol, "tol", allow_inf=False)
    for name, value in (("temperature", temperature), ("range_scale", range_scale)):
        _util.validate_nonneg(value, name, allow_inf=False)
        if _util.is_concrete(value) and float(value) == 0.0:
            raise ValueError(f"{name}: must be positive, got {value!r}")
    _util.validate_count(grid_size, "grid_size", 2, 10_000)
    _util.validate_count(newton_steps, "newton_steps", 0, 10_000)
    if dims is not None:
        dims = tuple(dims)
        if not dims or any((not isinstance(i, int)) or i < 0 or i >= dim for i in dims):
            raise ValueError(f"dims: expected distinct state indices in [0, {dim}), got {dims!r}")
        if len(set(dims)) != len(dims):
            raise ValueError(f"dims: indices must be distinct, got {dims!r}")


def search_aux(res: SearchResult, n_ref: Array) -> dict[str, Array]:
    """The ``info.aux`` entries of a confidence search (same keys for a fixed ``λ``)."""
    return {
        "lambda": res.lam,
        "n_clusters": res.n_clusters,
        "n_reference": n_ref,
        "lambda_grid": res.lam_grid,
        "eise_grid": res.eise_grid,
        "lambda_newton": res.lam_newton,
        "eise_newton": res.eise_newton,
        "iterations": res.iterations,
        "newton_ok": res.newton_ok,
        "used_fallback": res.used_fallback,
    }


def fixed_result(gm: GaussianMixture, lam: ArrayLike, labels: Array, value: Array,
                 merged: GaussianMixture, n: Array) -> SearchResult:
    """A :class:`SearchResult` for a clustering at a given ``λ`` (no search)."""
    dtype = gm.means.dtype
    lam = jnp.asarray(lam, dtype)
    nan = jnp.asarray(jnp.nan, dtype)
    return SearchResult(lam, value, labels, merged, n, lam[None], value[None], n[None], lam, value,
                        lam, value, nan, jnp.zeros((), jnp.int32), jnp.zeros((), bool),
                        jnp.zeros((), bool))


def pcm(
    gm: GaussianMixture,
    *,
    rho: Any = 0.9544,
    max_components: int | None = None,
    alpha: Any = 0.001,
    lam: Any = None,
    lambda_range: Sequence[Any] = (1.0, 3.0),
    grid_size: int = 11,
    newton_steps: int = 8,
    temperature: Any = 0.2,
    tol: Any = 1e-6,
    range_scale: Any = 0.5,
    dims: Sequence[int] | None = None,
    merge: str = "ci",
    prune: bool = True,
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """Prune-cluster-merge reduction (seed 000 Table 1 steps 2–7).

    Args:
        gm: input mixture, capacity ``K`` (weights normalised or not; eq 41 rescales the survivors
            to the input's total).
        rho: censoring threshold ``ρ`` of eqs 20–21 (traced; default 0.9544, the 2σ rule).
        max_components: static cap ``N_u`` of eq 22 (default none).
        alpha: regularisation constant ``α`` of eq 29 (§IV: 0.001).
        lam: a fixed confidence multiplier ``λ`` (``σ* = λσ``); ``None`` searches it (step 7).
        lambda_range: the search scope ``(low, high)`` (§IV-A: ``[1, 3]``).
        grid_size: static number of grid points of the search.
        newton_steps: static number of Newton–Raphson steps on the relaxed EISE (0: grid only).
        temperature: relaxation temperature ``τ`` (about the grid spacing).
        tol: Newton's stopping tolerance on ``|Δλ|`` and on the relative EISE change.
        range_scale: the confidence scope is ``range_scale · λσ`` (see
            :mod:`gmjax.reduction._clustering`; 0.5 reproduces the papers' cluster counts).
        dims: static state dimensions to cluster on (seed 000 §IV-D: position only); merging and
            the EISE use the full state.
        merge: ``"ci"`` (eqs 38–39, the paper) or ``"moment"``.
        prune: static; ``False`` skips step 2 (as in the search-scope study of §IV-A).
        capacity: static output capacity (default ``K``); if more clusters survive, the heaviest
            are kept and ``info.overflow`` is set.
        key: unused (Reducer protocol).

    Returns:
        ``(reduced, info)``: ``info.cost`` is the EISE at ``λ*``; ``info.aux`` holds ``lambda``
        (``λ*``), ``n_clusters`` (``N'``), ``n_reference`` (``N``, components after pruning),
        ``lambda_grid``/``eise_grid`` (grid's best), ``lambda_newton``/``eise_newton`` (where
        Newton stopped, hard EISE there), ``iterations``, ``newton_ok`` and ``used_fallback``.

    Raises:
        ValueError: for a bad concrete mixture or an invalid option, naming the argument.
    """
    del key
    _util.validate_mixture(gm)
    _util.validate_range(rho, "rho", 0.0, 1.0)
    if merge not in ("ci", "moment"):
        raise ValueError(f"merge: expected 'ci' or 'moment', got {merge!r}")
    validate_search_args(lam=lam, lambda_range=lambda_range, alpha=alpha, temperature=temperature,
                         tol=tol, range_scale=range_scale, grid_size=grid_size,
                         newton_steps=newton_steps, dims=dims, dim=gm.dim)
    if max_components is not None:
        max_components = _util.validate_count(max_components, "max_components", 1, 2**31 - 1)
    cap = _util.validate_capacity(capacity, gm)
    dims = None if dims is None else tuple(dims)

    return _pcm_core(gm, rho, alpha, lam, tuple(lambda_range), temperature, tol, range_scale,
                     max_components=max_components, grid_size=grid_size,
                     newton_steps=newton_steps, dims=dims, merge=merge, prune=prune, capacity=cap)


@partial(jax.jit, static_argnames=("max_components", "grid_size", "newton_steps", "dims", "merge",
                                   "prune", "capacity"))
def _pcm_core(gm, rho, alpha, lam, lambda_range, temperature, tol, range_scale, *,
              max_components, grid_size, newton_steps, dims, merge, prune, capacity):
    K = gm.capacity
    slots = jnp.arange(K, dtype=jnp.int32)
    # At most N_u components survive the pruning, so cluster and merge in N_u slots: the overlap
    # sweep and the EISE cost O(K_w^2) per pair visit, and K_w = N_u is usually far below K.
    Kw = K if (not prune or max_components is None) else min(K, max_components)
    if prune:
        work, pinfo = prune_censored(gm, rho, max_components, capacity=Kw)
        to_work = pinfo.labels
        pruned_mass = pinfo.pruned_mass
    else:
        work = gm
        to_work = jnp.where(gm.mask, slots, -1)
        pruned_mass = jnp.zeros((), gm.weights.dtype)
    n_ref = jnp.sum(work.mask.astype(jnp.int32))

    if lam is None:
        res = search_confidence(
            work, lam_lo=lambda_range[0], lam_hi=lambda_range[1], grid_size=grid_size,
            newton_steps=newton_steps, temperature=temperature, tol=tol, alpha=alpha,
            method=merge, regularizer="exp", ise_scale=0.5, dims=dims, triangular=False,
            subset_rule="split", range_scale=range_scale,
        )
    else:
        cl = gauss_cluster(work, lam, dims=dims, range_scale=range_scale)
        value, merged, n = hard_eise(work, cl.labels, alpha=alpha, method=merge,
                                     regularizer="exp", ise_scale=0.5)
        res = fixed_result(work, lam, cl.labels, value, merged, n)

    merged = merge_labels(work, res.labels, Kw, merge)  # output slot = cluster head (eqs 38–39)
    labels_in = jnp.where(to_work >= 0, res.labels[jnp.maximum(to_work, 0)], -1)
    out, labels_out, overflow, _ = _util.finalize(gm, merged, labels_in, capacity)
    info = make_info(gm, out, labels_out, pruned_mass=pruned_mass, overflow=overflow,
                     cost=res.eise, aux=search_aux(res, n_ref))
    return out, info


@pytree_dataclass
class PCM:
    """Reducer config for :func:`pcm` (static: sizes and step counts; the rest are traced).

    ``PCM()(gm)`` runs the paper's reduction with the searched ``λ``; set ``lam`` to fix it.
    """

    rho: Any = 0.9544
    alpha: Any = 0.001
    lam: Any = None
    lambda_range: Any = (1.0, 3.0)
    temperature: Any = 0.2
    tol: Any = 1e-6
    range_scale: Any = 0.5
    max_components: int | None = static_field(None)
    grid_size: int = static_field(11)
    newton_steps: int = static_field(8)
    dims: tuple[int, ...] | None = static_field(None)
    merge: str = static_field("ci")
    prune: bool = static_field(True)
    capacity: int | None = static_field(None)

    def __call__(self, gm: GaussianMixture, *, key: jax.Array | None = None):
        return pcm(
            gm, rho=self.rho, max_components=self.max_components, alpha=self.alpha, lam=self.lam,
            lambda_range=self.lambda_range, grid_size=self.grid_size,
            newton_steps=self.newton_steps, temperature=self.temperature, tol=self.tol,
            range_scale=self.range_scale, dims=self.dims, merge=self.merge, prune=self.prune,
            capacity=self.capacity, key=key,
        )
