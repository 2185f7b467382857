"""Prune-cluster-merge mixture reduction, PCM-GMR (Xu et al., PCM = seed 000, Table 1 steps 2–7).

1. *Weight-censored pruning* by the j-th order statistic (eqs 19–22, ``ρ = 0.9544``, cap ``N_u``)
   with the survivors' weights reset by eq 41 (:func:`gmjax.reduction.prune.prune_censored`).
2. *Gauss clustering* by the distribution-similarity criterion at confidence range ``σ* = λσ``
   (eqs 23–28, :mod:`gmjax.reduction.clustering`).
3. *Covariance-intersection merging* of every cluster with the normalised weights (eqs 38–39, 41).
4. *Confidence-range search*: ``λ`` minimising the EISE ``½ Σ_c ∫ (f_c - q_c)² + α e^{N'/N}``
   (eqs 29–35) over the scope ``[1, 3]`` (§IV-A), by a grid and Newton–Raphson steps on a smooth
   relaxation (:mod:`gmjax.reduction.eise`; the hard EISE is piecewise constant in ``λ``, so Newton
   needs the relaxation), falling back to the grid's best.

Everything is a fixed-capacity array program: ``jit``, ``vmap`` over mixtures, and ``lax.scan`` in a
filter work, and ``λ``, ``ρ``, ``α`` and the temperatures are traced config fields.

**Relaxation** (DESIGN §3; for differentiating a Monte Carlo loss in ``ρ`` and a fixed ``λ``). The
static ``mode`` is ``"hard"`` (default: the paper's reduction above), ``"soft"`` or
``"straight_through"``; the relaxed modes need a fixed ``lam``. Two temperatures, one per decision:

* ``gate_temperature`` ``T_ρ`` (probability-mass units) relaxes step 2, the censored pruning, into
  sigmoid gates (:func:`gmjax.reduction.relax.censored_gates`, as
  ``PruneCensored(mode=..., temperature=T_ρ)``);
* ``temperature`` ``τ`` (units of ``λ``) is the *same* relaxation of the clustering that the
  confidence search uses: the kernel-smoothed memberships ``A(λ) = Σ_g π_g(λ) A_g`` over the grid
  of ``grid_size`` points on ``lambda_range`` (:func:`gmjax.reduction.relax.soft_membership`). With
  ``lam=None`` it smooths the EISE for Newton (and must be positive); with a fixed ``lam`` in a
  relaxed mode every soft cluster is merged with its fractional memberships and costed by the
  relaxed EISE (eq 29), and ``τ = 0`` is the hard clustering at ``lam``.

``mode="soft"`` with ``T_ρ = τ = 0`` equals ``"hard"`` with the same ``lam`` exactly;
``"straight_through"`` returns the hard output with the relaxation's gradient.
"""

from __future__ import annotations

import dataclasses
import sys
from functools import partial
from typing import Any, Mapping

import jax
import jax.numpy as jnp

from gmjax import _validate
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array
from gmjax.mixture import GaussianMixture, sanitize
from gmjax.reduction import _util
from gmjax.reduction.base import ReductionInfo, Stateless, calls, make_info
from gmjax.reduction.eise import (
    ConfidenceSearch,
    SearchOptions,
    SearchResult,
    eise,
    hard_eise,
    merge_membership,
    onehot_membership,
)
from gmjax.reduction.eise.search import _SearchSettings
from gmjax.reduction.merge import merge_labels
from gmjax.reduction.prune import prune_censored
from gmjax.reduction.relax import (
    censored_gates,
    gated_prune,
    negligible_floor,
    soft_membership,
    straight_through,
    validate_mode,
    validate_temperature,
)

if sys.version_info >= (3, 11):
    from typing import Unpack
else:  # pragma: no cover - Python 3.10
    from typing_extensions import Unpack

__all__ = ["pcm", "PCM", "search_aux", "validate_search_args", "checked_search"]


def validate_search_args(
    search: ConfidenceSearch, lam: Any, dim: int, *, allow_zero_temperature: bool = False
) -> None:
    """Eager ``ValueError`` checks of a confidence search built from :func:`pcm`'s or ``gmrcm``'s
    arguments, naming the argument (no-op on tracers); ``dim`` is the mixture's dimension.

    ``temperature`` must be positive (it smooths the search's EISE), or non-negative with
    ``allow_zero_temperature`` (PCM's relaxed modes at a fixed ``λ``, where 0 is the hard rule).
    """
    lambda_range = search.lambda_range
    if len(tuple(lambda_range)) != 2:
        raise ValueError(f"lambda_range: expected (low, high), got {lambda_range!r}")
    lo, hi = lambda_range
    _validate.validate_nonneg(lo, "lambda_range")
    _validate.validate_nonneg(hi, "lambda_range")
    if _validate.is_concrete(lo, hi) and not float(lo) < float(hi):
        raise ValueError(f"lambda_range: need low < high, got {lambda_range!r}")
    if lam is not None:
        _validate.validate_nonneg(lam, "lam", allow_inf=False)
    _validate.validate_nonneg(search.alpha, "alpha", allow_inf=False)
    _validate.validate_nonneg(search.tol, "tol", allow_inf=False)
    for name, value in (("temperature", search.temperature), ("range_scale", search.range_scale)):
        _validate.validate_nonneg(value, name, allow_inf=False)
        if name == "temperature" and allow_zero_temperature:
            continue
        if _validate.is_concrete(value) and float(value) == 0.0:
            raise ValueError(f"{name}: must be positive, got {value!r}")
    _validate.validate_count(search.grid_size, "grid_size", 2, 10_000)
    _validate.validate_count(search.newton_steps, "newton_steps", 0, 10_000)
    dims = search.dims
    if dims is not None:
        if not dims or any((not isinstance(i, int)) or i < 0 or i >= dim for i in dims):
            raise ValueError(f"dims: expected distinct state indices in [0, {dim}), got {dims!r}")
        if len(set(dims)) != len(dims):
            raise ValueError(f"dims: indices must be distinct, got {dims!r}")


def checked_search(
    gm: GaussianMixture,
    lam: Any,
    defaults: ConfidenceSearch,
    options: Mapping[str, Any],
    *,
    caller: str,
    allow_zero_temperature: bool = False,
) -> tuple[ConfidenceSearch, Any, Array | None]:
    """The confidence search of :func:`pcm` and ``gmrcm``: their paper's ``defaults`` with the
    caller's ``options`` (:class:`~gmjax.reduction.eise.SearchOptions`) in place, traced NaNs
    replaced (:func:`gmjax.reduction._util.replace_nans`; the stand-ins are :meth:`ConfidenceSearch.seed000`'s
    values and ``lam = 2``), the concrete values checked (:func:`validate_search_args`).

    Returns:
        ``(search, lam, bad)``: ``bad`` is the traced "some argument was NaN" (``None`` when none
        was traced), for :func:`gmjax.reduction._util.unchanged_if_nan`.

    Raises:
        TypeError: for an option that is not a search setting, as Python words it for ``caller``.
    """
    for name in options:
        if name not in SearchOptions.__annotations__:
            raise TypeError(f"{caller}() got an unexpected keyword argument {name!r}")
    search = dataclasses.replace(defaults, **options)
    (lam, lambda_range, alpha, temperature, tol, range_scale), bad = _util.replace_nans(
        (lam, 2.0),
        (search.lambda_range, 2.0),
        (search.alpha, 1e-3),
        (search.temperature, 0.2),
        (search.tol, 1e-6),
        (search.range_scale, 0.5),
    )
    search = dataclasses.replace(
        search,
        lambda_range=tuple(lambda_range),
        alpha=alpha,
        temperature=temperature,
        tol=tol,
        range_scale=range_scale,
        dims=None if search.dims is None else tuple(search.dims),
    )
    validate_search_args(search, lam, gm.dim, allow_zero_temperature=allow_zero_temperature)
    return search, lam, bad


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


def pcm(
    gm: GaussianMixture,
    *,
    rho: Any = 0.9544,
    max_components: int | None = None,
    lam: Any = None,
    merge: str = "ci",
    prune: bool = True,
    capacity: int | None = None,
    gate_temperature: Any = 0.0,
    mode: str = "hard",
    key: jax.Array | None = None,
    **search: Unpack[SearchOptions],
) -> tuple[GaussianMixture, ReductionInfo]:
    """Prune-cluster-merge reduction (seed 000 Table 1 steps 2–7), optionally relaxed.

    Args:
        gm: input mixture, capacity ``K`` (weights normalised or not; eq 41 rescales the survivors
            to the input's total).
        rho: censoring threshold ``ρ`` of eqs 20–21 (traced; default 0.9544, the 2σ rule).
        max_components: static cap ``N_u`` of eq 22 (default none).
        lam: a fixed confidence multiplier ``λ`` (``σ* = λσ``); ``None`` searches it (step 7).
        merge: ``"ci"`` (eqs 38–39, the paper) or ``"moment"``.
        prune: static; ``False`` skips step 2 (as in the search-scope study of §IV-A).
        capacity: static output capacity (default ``K``); if more clusters survive, the heaviest
            are kept and ``info.overflow`` is set.
        gate_temperature: ``T_ρ >= 0`` of the relaxed pruning gates, in units of probability mass
            (traced; unused when ``mode="hard"``).
        mode: static ``"hard"`` (default), ``"soft"`` or ``"straight_through"`` (module docstring;
            the relaxed modes need a fixed ``lam``).
        key: unused (Reducer protocol).
        **search: the confidence search (:class:`~gmjax.reduction.eise.SearchOptions`; the
            defaults are :meth:`ConfidenceSearch.seed000`'s):

            * ``alpha``: regularisation constant ``α`` of eq 29 (§IV: 0.001);
            * ``lambda_range``: the search scope ``(low, high)`` (§IV-A: ``(1, 3)``);
            * ``grid_size``: static number of grid points (11);
            * ``newton_steps``: static number of Newton–Raphson steps on the relaxed EISE (8; 0:
              grid only);
            * ``temperature``: relaxation temperature ``τ`` of the clustering in units of ``λ``
              (0.2, about the grid spacing): the search's relaxed EISE when ``lam`` is ``None``
              (must be positive), the soft memberships at ``lam`` in the relaxed modes (``>= 0``;
              0 is hard);
            * ``tol``: Newton's stopping tolerance on ``|Δλ|`` and on the relative EISE change
              (1e-6);
            * ``range_scale``: the confidence scope is ``range_scale · λσ`` (0.5, which reproduces
              the papers' cluster counts; see :mod:`gmjax.reduction.clustering`);
            * ``dims``: static state dimensions to cluster on (seed 000 §IV-D: position only;
              default all); merging and the EISE use the full state.

    Returns:
        ``(reduced, info)``: ``info.cost`` is the EISE at ``λ*``; ``info.aux`` holds ``lambda``
        (``λ*``), ``n_clusters`` (``N'``), ``n_reference`` (``N``, components after pruning),
        ``lambda_grid``/``eise_grid`` (grid's best), ``lambda_newton``/``eise_newton`` (where
        Newton stopped, hard EISE there), ``iterations``, ``newton_ok`` and ``used_fallback``.
        In the relaxed modes (see :func:`_soft_pcm_core`) ``info.cost`` is the relaxed EISE and
        ``info.aux`` holds ``lambda``, ``n_clusters`` (hard ``N'``), ``n_reference`` (survivors of
        the gated pruning), ``n_expected`` (expected output size, ``N'`` at zero temperatures) and
        ``n_pruned_expected`` (``Σ`` of the pruning gates).

    Raises:
        ValueError: for a bad concrete mixture or an invalid option, naming the argument.
        TypeError: for a keyword that is neither an argument above nor a search setting.
    """
    del key
    (rho, gate_temperature), bad = _util.replace_nans((rho, 0.9544), (gate_temperature, 0.0))
    _validate.validate_mixture(gm)
    _validate.validate_range(rho, "rho", 0.0, 1.0)
    if merge not in ("ci", "moment"):
        raise ValueError(f"merge: expected 'ci' or 'moment', got {merge!r}")
    validate_mode(mode)
    if mode != "hard" and lam is None:
        raise ValueError(
            f"lam: mode={mode!r} needs a fixed lam (the searched λ* is an argmin of a "
            "piecewise-constant EISE, with no useful gradient); set lam=..."
        )
    validate_temperature(gate_temperature, "gate_temperature")
    confidence, lam, bad_search = checked_search(
        gm, lam, ConfidenceSearch.seed000(merge), search, caller="pcm", allow_zero_temperature=mode != "hard"
    )
    if max_components is not None:
        max_components = _validate.validate_count(max_components, "max_components", 1, 2**31 - 1)
    cap = _validate.validate_capacity(capacity, gm)
    core = _pcm_core if mode == "hard" else partial(_soft_pcm_core, mode=mode)
    out = core(
        gm, rho, lam, confidence, gate_temperature, max_components=max_components, prune=prune, capacity=cap
    )
    return _util.unchanged_if_nan(_util.either(bad, bad_search), gm, out)


@partial(jax.jit, static_argnames=("max_components", "prune", "capacity"))
def _pcm_core(gm, rho, lam, search, gate_temperature, *, max_components, prune, capacity):
    del gate_temperature  # the relaxed modes' (one signature for both cores)
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

    res = search(work, lam)  # step 7: searched (lam None) or at the given λ
    # output slot = cluster head (eqs 38–39)
    merged = merge_labels(work, res.labels, Kw, search.criterion.method)
    labels_in = jnp.where(to_work >= 0, res.labels[jnp.maximum(to_work, 0)], -1)
    out, labels_out, overflow, _ = _util.finalize(gm, merged, labels_in, capacity)
    info = make_info(
        gm,
        out,
        labels_out,
        pruned_mass=pruned_mass,
        overflow=overflow,
        cost=res.eise,
        aux=search_aux(res, n_ref),
    )
    return out, info


def _tree_select(pred, a, b):
    return jax.tree_util.tree_map(lambda x, y: jnp.where(pred, x, y), a, b)


def _gated_step(gm, rho, gate_temperature, relaxed, *, max_components, prune, mode, Kw):
    """Step 2 with soft gates: ``(work, gates of work's slots, to_work labels, pruned mass,
    overflow, Σ gates)``; ``prune=False`` passes ``gm`` through with unit gates."""
    dtype = gm.means.dtype
    if not prune:
        live = gm.mask.astype(dtype)
        slots = jnp.arange(gm.capacity, dtype=jnp.int32)
        return (
            gm,
            live,
            jnp.where(gm.mask, slots, -1),
            jnp.zeros((), gm.weights.dtype),
            jnp.zeros((), bool),
            jnp.sum(live),
        )
    gates = censored_gates(gm, rho, gate_temperature, max_components=max_components, mode=mode)
    # a relaxed reducer (T_ρ or τ > 0) drops negligible components (see gated_prune)
    floor = jnp.where(relaxed, negligible_floor(1.0, mode, dtype), 0.0)
    work, pinfo = gated_prune(gm, gates, Kw, floor)
    return (
        work,
        pinfo.aux["gates"],
        pinfo.labels,
        pinfo.pruned_mass,
        pinfo.overflow,
        pinfo.aux["n_expected"],
    )


@partial(jax.jit, static_argnames=("max_components", "prune", "mode", "capacity"))
def _soft_pcm_core(gm, rho, lam, search, gate_temperature, *, max_components, prune, mode, capacity):
    """PCM at a fixed ``λ`` with relaxed pruning and relaxed memberships (``mode`` soft / ST).

    The pruning uses :func:`censored_gates` (``T_ρ``) and the clustering :func:`soft_membership`
    over the grid of ``grid_size`` points on ``lambda_range`` (``τ``); each cluster is merged with
    the fractional memberships (:func:`gmjax.reduction.eise.merge_membership`, eqs 38–39 with
    weights ``A_mc w_m``), and the cost is the EISE of eq 29 on the soft clusters (the relaxation
    PCM's search minimises). With ``τ = 0`` the clustering, merge and cost are exactly the hard
    ones at ``λ``; with ``T_ρ = 0`` too the output equals ``pcm(gm, rho=ρ, lam=λ)``.

    Soft clusters: every cluster that some grid clustering forms near ``λ`` is an output slot with
    its soft weight, so the relaxed output has more (light) components than the hard one; its
    expected size is ``n_expected = Σ_g π_g Σ_c max_{m ∈ c_g} gate_m`` (a cluster exists when a
    member survives the pruning), which equals ``N'`` at ``τ = T_ρ = 0``.
    """
    dtype = gm.means.dtype
    K = gm.capacity
    Kw = K if (not prune or max_components is None) else min(K, max_components)
    alpha, merge = search.alpha, search.criterion.method
    T_lam = jnp.asarray(search.temperature, dtype)
    relaxed = (jnp.asarray(gate_temperature, dtype) > 0) | (T_lam > 0)
    work, g_work, to_work, pruned_mass, p_overflow, n_gates = _gated_step(
        gm, rho, gate_temperature, relaxed, max_components=max_components, prune=prune, mode=mode, Kw=Kw
    )
    n_ref = jnp.sum(work.mask.astype(jnp.int32))
    lo, hi = (jnp.asarray(v, dtype) for v in search.lambda_range)
    grid = lo + (hi - lo) * jnp.linspace(0.0, 1.0, search.grid_size, dtype=dtype)
    lam = jnp.asarray(lam, dtype)
    A, pi, grid_labels, labels = soft_membership(
        work, lam, grid, T_lam, dims=search.dims, range_scale=search.range_scale
    )

    # hard clustering at λ: exactly pcm(lam=λ)'s merge and EISE
    merged_hard = merge_labels(work, labels, Kw, merge)
    value_hard, _, n_hard = hard_eise(
        work, labels, alpha=alpha, method=merge, regularizer="exp", ise_scale=0.5
    )
    n_hard_f = n_hard.astype(dtype)

    # soft clusters: fractional merge (eqs 38–39 with weights A_mc w_m) and the relaxed EISE (eq 29)
    A_live = jnp.where(work.mask[:, None], A, 0.0)
    merged_soft = merge_membership(work, A_live, merge)
    onehots = jax.vmap(lambda lab: onehot_membership(lab, Kw, dtype))(grid_labels)  # (G, K, C)
    exists = jnp.max(onehots * g_work[None, :, None], axis=1)  # (G, C)
    n_soft = jnp.sum(pi[:, None] * exists)
    value_soft = eise(
        work, A_live, merged_soft, n_soft, n_ref, alpha=alpha, regularizer="exp", ise_scale=0.5, clip=False
    )
    soft_on = T_lam > 0  # τ = 0: the hard clustering, merged and costed exactly as pcm does
    soft_f = _tree_select(soft_on, merged_soft, merged_hard)
    soft_n = jnp.where(soft_on, n_soft, n_hard_f)
    soft_v = jnp.where(soft_on, value_soft, value_hard)
    if mode == "soft":
        merged, value, n_exp = soft_f, soft_v, soft_n
    else:  # straight-through: the hard clusters' values, the soft clusters' gradients
        both = merged_hard.mask & soft_f.mask
        st = lambda h, s: jnp.where(  # noqa: E731
            both.reshape(both.shape + (1,) * (h.ndim - 1)), straight_through(h, s), h
        )
        merged = GaussianMixture(
            st(merged_hard.weights, soft_f.weights),
            st(merged_hard.means, soft_f.means),
            st(merged_hard.covs, soft_f.covs),
            merged_hard.mask,
        )
        value = straight_through(value_hard, soft_v)
        n_exp = straight_through(n_hard_f, soft_n)
    merged = sanitize(merged)
    labels_in = jnp.where(to_work >= 0, labels[jnp.maximum(to_work, 0)], -1)
    out, labels_out, overflow, _ = _util.finalize(gm, merged, labels_in, capacity)
    aux = {
        "lambda": lam,
        "n_clusters": n_hard,
        "n_reference": n_ref,
        "n_expected": n_exp,
        "n_pruned_expected": n_gates,
    }
    info = make_info(
        gm, out, labels_out, pruned_mass=pruned_mass, overflow=overflow | p_overflow, cost=value, aux=aux
    )
    return out, info


@pytree_dataclass
class PCM(_SearchSettings, Stateless):
    """Reducer config for :func:`pcm` (static: sizes, step counts, ``mode``; the rest are traced):
    :func:`pcm`'s arguments, its search settings (``lambda_range``, ``alpha``, ``temperature``,
    ``tol``, ``range_scale``, ``grid_size``, ``newton_steps``, ``dims``) included.

    ``PCM()(gm)`` runs the paper's reduction with the searched ``λ``; set ``lam`` to fix it.
    ``PCM(rho=ρ, lam=λ, mode="soft", gate_temperature=T_ρ, temperature=τ)`` is the relaxed
    reduction, differentiable in ``ρ`` and ``λ`` (module docstring); zero temperatures give
    ``PCM(rho=ρ, lam=λ)`` exactly.
    """

    rho: Any = 0.9544
    lam: Any = None
    max_components: int | None = static_field(None)
    merge: str = static_field("ci")
    prune: bool = static_field(True)
    capacity: int | None = static_field(None)
    gate_temperature: Any = 0.0
    mode: str = static_field("hard")

    __call__ = calls(pcm)
