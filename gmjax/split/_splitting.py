"""Splitting Gaussians and padded mixtures with a library along a direction (traceable, seed 002 eq 20).

A Gaussian ``N(m, P)`` is split along a split column ``a`` (:func:`~gmjax.split.split_axis`: the
principal axis, a coordinate or a vector) into ``sum_i w_i N(m + mu_i a, P - (1 - sigma^2) a a^T)``:
one Gaussian (:func:`~gmjax.split.split_gaussian`), every slot of a mixture once or repeatedly
(:func:`~gmjax.split.split_mixture`, :func:`~gmjax.split.split_repeated`, seed 001's
:func:`~gmjax.split.split_principal`), or the selected slots inside a fixed capacity
(:func:`~gmjax.split.refine`, :class:`~gmjax.split.RefineInfo`). :mod:`gmjax.split` states the split.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import gaussian
from gmjax._types import Array, ArrayLike, Vector
from gmjax.mixture import GaussianMixture, sanitize
from gmjax.split._libraries import SplitLibrary, principal_library


class RefineInfo(NamedTuple):
    """What :func:`refine` did.

    Attributes:
        n_split: ``()`` int32, number of slots that were split.
        n_out: ``()`` int32, live components after refinement.
        overflow: ``()`` bool, True when some selected slots could not be split for lack of free
            slots (the heaviest selected slots were split first).
    """

    n_split: Array
    n_out: Array
    overflow: Array


# ----------------------------------------------------------------------------------------------
# Splitting (traceable)
# ----------------------------------------------------------------------------------------------


def split_axis(cov: ArrayLike, direction: int | ArrayLike | None = None) -> Vector:
    """The split column ``a`` (``(d,)``) of a covariance for a direction choice.

    Args:
        cov: ``(d, d)`` covariance.
        direction: ``None`` for the principal axis ``sqrt(lambda_max) e_max``; an ``int`` ``i`` for
            ``P e_i / sqrt(P_ii)``; a ``(d,)`` vector ``u`` for ``P u / sqrt(u^T P u)``.

    Returns:
        ``a`` with ``P - a a^T`` positive semi-definite.
    """
    cov = gaussian.symmetrize(jnp.asarray(cov))
    d = cov.shape[-1]
    if direction is None:
        lam, vecs = jnp.linalg.eigh(cov)
        lam_max = jnp.maximum(lam[-1], 0.0)
        return jnp.sqrt(lam_max) * vecs[:, -1]
    if isinstance(direction, (int, np.integer)):
        if not 0 <= int(direction) < d:
            raise ValueError(f"direction: axis {direction} out of range for dimension {d}")
        u = jnp.zeros(d, cov.dtype).at[int(direction)].set(1.0)
    else:
        u = jnp.asarray(direction, cov.dtype)
        if u.shape != (d,):
            raise ValueError(f"direction: expected a ({d},) vector, got shape {u.shape}")
    Pu = cov @ u
    s2 = u @ Pu
    ok = s2 > 0
    return jnp.where(ok, Pu / jnp.sqrt(jnp.where(ok, s2, 1.0)), 0.0)


def _lib_arrays(library: SplitLibrary, dtype) -> tuple[Array, Array, Array]:
    return (
        jnp.asarray(library.weights, dtype),
        jnp.asarray(library.means, dtype),
        jnp.asarray(library.sigma, dtype),
    )


def _split_one(weight, mean, cov, library: SplitLibrary, direction):
    dtype = jnp.result_type(mean, cov)
    lw, lm, ls = _lib_arrays(library, dtype)
    a = split_axis(cov, direction)
    means = mean[None, :] + lm[:, None] * a[None, :]
    child_cov = gaussian.symmetrize(cov - (1.0 - ls * ls) * jnp.outer(a, a))
    covs = jnp.broadcast_to(child_cov, (lw.shape[0],) + cov.shape)
    return weight * lw, means, covs


def split_gaussian(
    weight: ArrayLike,
    mean: ArrayLike,
    cov: ArrayLike,
    library: SplitLibrary,
    direction: int | ArrayLike | None = 0,
) -> GaussianMixture:
    """Split one weighted Gaussian with a 1-D library along a direction (seed 002 eq 20).

    Args:
        weight: ``()`` weight of the component (children get ``weight * w_i``).
        mean: ``(d,)``. cov: ``(d, d)``.
        library: a :class:`SplitLibrary` with ``M`` components.
        direction: see :func:`split_axis` (default: coordinate 0).

    Returns:
        A ``M``-component mixture ``sum_i weight w_i N(mean + mu_i a, cov - (1 - sigma^2) a a^T)``.
    """
    mean = jnp.asarray(mean)
    cov = jnp.asarray(cov, mean.dtype)
    spec, u = _direction_spec(direction, mean.shape[-1])
    one = GaussianMixture(jnp.asarray(weight, mean.dtype)[None], mean[None], cov[None], jnp.ones(1, bool))
    return _split_mixture_jit(one, library, u, spec)


def _direction_spec(direction, d: int):
    """Split a direction into a static part (kind, axis) and a dynamic vector (for jit)."""
    if direction is None:
        return ("principal", 0), None
    if isinstance(direction, (int, np.integer)):
        if not 0 <= int(direction) < d:
            raise ValueError(f"direction: axis {direction} out of range for dimension {d}")
        return ("axis", int(direction)), None
    u = jnp.asarray(direction)
    if u.shape != (d,):
        raise ValueError(f"direction: expected a ({d},) vector, got shape {u.shape}")
    return ("vector", 0), u


def _resolve(spec, u):
    kind, axis = spec
    if kind == "principal":
        return None
    if kind == "axis":
        return axis
    return u


@partial(jax.jit, static_argnames=("spec",))
def _split_mixture_jit(gm: GaussianMixture, library: SplitLibrary, u, spec) -> GaussianMixture:
    M = library.weights.shape[0]
    K, d = gm.capacity, gm.dim
    direction = _resolve(spec, u)
    # Padded slots: replace the (degenerate, identity) covariance by diag(1..d) before eigh so that
    # gradients stay finite; their children are sanitised afterwards.
    safe_cov = jnp.where(gm.mask[:, None, None], gm.covs, jnp.diag(jnp.arange(1, d + 1, dtype=gm.covs.dtype)))
    w, m, P = jax.vmap(lambda a, b, c: _split_one(a, b, c, library, direction))(
        gm.weights, gm.means, safe_cov
    )
    mask = jnp.repeat(gm.mask, M)
    out = GaussianMixture(w.reshape(K * M), m.reshape(K * M, d), P.reshape(K * M, d, d), mask)
    return sanitize(out)


def split_mixture(
    gm: GaussianMixture, library: SplitLibrary, direction: int | ArrayLike | None = 0
) -> GaussianMixture:
    """Split every slot of a mixture with a library: capacity ``K -> K M`` (children parent-major).

    Padded parents give padded children; live weights are multiplied by the library weights, so the
    total weight is unchanged. Compiled once per shape and direction kind.
    """
    spec, u = _direction_spec(direction, gm.dim)
    return _split_mixture_jit(gm, library, u, spec)


def split_repeated(
    gm: GaussianMixture,
    library: SplitLibrary,
    directions: Sequence[int | ArrayLike | None],
) -> GaussianMixture:
    """Apply :func:`split_mixture` once per entry of ``directions`` (capacity ``K M^len``).

    Repeated splitting gives the multidirectional GMM of seed 002 §III-A; e.g. the 1-D benchmark
    splits ``N(0, 1)`` four times along axis 0 with the ``sigma = 1/2, M = 8`` library (4096 terms).
    """
    for direction in directions:
        gm = split_mixture(gm, library, direction)
    return gm


def split_principal(
    weight: ArrayLike,
    mean: ArrayLike,
    cov: ArrayLike,
    n_split: int,
    l: float = 0.5,  # noqa: E741
    w: float = 0.5,
) -> GaussianMixture:
    """Seed 001 eq 32 repeated ``n_split`` times: ``N_F = 2^n_split`` components.

    Each pass splits every current component in two along the eigenvector of its own largest
    eigenvalue: ``mu +- l sqrt(lambda) e_v``, covariance ``Sigma - l^2 lambda e_v e_v^T``, weights
    ``w`` and ``1 - w`` (seed 001 §3.3, Step 3).

    Args:
        weight: ``()`` weight of the component being split.
        mean: ``(d,)``. cov: ``(d, d)``.
        n_split: ``n >= 0`` (static); ``0`` returns the component itself.
        l: displacement, ``0 < l < 1`` (paper: 0.5). w: weight ``omega`` (paper: 0.5).

    Returns:
        A mixture of ``2^n_split`` components whose weights sum to ``weight``.
    """
    if int(n_split) != n_split or n_split < 0:
        raise ValueError(f"n_split: must be a non-negative integer, got {n_split}")
    lib = principal_library(l, w)
    mean = jnp.asarray(mean)
    cov = jnp.asarray(cov, mean.dtype)
    gm = GaussianMixture(jnp.asarray(weight, mean.dtype)[None], mean[None], cov[None], jnp.ones(1, bool))
    return split_repeated(gm, lib, [None] * int(n_split))


def refine(
    gm: GaussianMixture,
    mask_to_split: ArrayLike,
    library: SplitLibrary,
    capacity: int | None = None,
    *,
    direction: int | ArrayLike | None = None,
) -> tuple[GaussianMixture, RefineInfo]:
    """Split the selected slots of a mixture inside a fixed capacity.

    Each selected live slot is replaced by its ``M`` children. The output lists the live slots in
    their original order, compacted to the front, with every split slot expanded in place into its
    children (so the slots after it shift); padded slots follow. When free slots run short, the
    heaviest selected slots are split first and ``info.overflow`` is set; nothing is ever dropped.

    Args:
        gm: mixture of capacity ``K``.
        mask_to_split: ``(K,)`` bool, which slots to split (padded slots are ignored).
        library: the splitting library (e.g. :func:`principal_library` for seed 001).
        capacity: output capacity ``C >= K`` (static; default ``K``).
        direction: see :func:`split_axis` (default: principal axis).

    Returns:
        ``(mixture of capacity C, RefineInfo)``.
    """
    K, d = gm.capacity, gm.dim
    C = K if capacity is None else int(capacity)
    if C < K:
        raise ValueError(f"capacity: {C} is smaller than the mixture capacity {K}")
    sel_in = jnp.asarray(mask_to_split, bool)
    if sel_in.shape != (K,):
        raise ValueError(f"mask_to_split: expected shape ({K},), got {sel_in.shape}")
    spec, u = _direction_spec(direction, d)
    return _refine_jit(gm, sel_in, library, u, spec=spec, capacity=C)


@partial(jax.jit, static_argnames=("spec", "capacity"))
def _refine_jit(gm, sel_in, library, u, *, spec, capacity):
    K, d = gm.capacity, gm.dim
    C = capacity
    M = library.weights.shape[0]
    sel = sel_in & gm.mask
    free = C - jnp.sum(gm.mask.astype(jnp.int32))
    # rank the selected slots by weight (heaviest first); the r-th needs (r + 1)(M - 1) free slots
    prio = jnp.where(sel, gm.weights, -jnp.inf)
    order = jnp.argsort(-prio, stable=True)
    rank = jnp.zeros(K, jnp.int32).at[order].set(jnp.arange(K, dtype=jnp.int32))
    allowed = sel & ((rank + 1) * (M - 1) <= free)
    children = _split_mixture_jit(gm, library, u, spec)
    cw = children.weights.reshape(K, M)
    cm = children.means.reshape(K, M, d)
    cP = children.covs.reshape(K, M, d, d)
    keep_w = jnp.zeros((K, M), gm.weights.dtype).at[:, 0].set(gm.weights)
    keep_m = jnp.zeros((K, M, d), gm.means.dtype).at[:, 0].set(gm.means)
    keep_P = jnp.broadcast_to(jnp.eye(d, dtype=gm.covs.dtype), (K, M, d, d)).at[:, 0].set(gm.covs)
    first_only = jnp.arange(M) == 0
    w = jnp.where(allowed[:, None], cw, keep_w)
    m = jnp.where(allowed[:, None, None], cm, keep_m)
    P = jnp.where(allowed[:, None, None, None], cP, keep_P)
    live = gm.mask[:, None] & (allowed[:, None] | first_only[None, :])
    flat_live = live.reshape(K * M)
    pos = jnp.cumsum(flat_live.astype(jnp.int32)) - 1
    dest = jnp.where(flat_live, pos, C)  # dead entries go out of bounds and are dropped
    eye = jnp.eye(d, dtype=gm.covs.dtype)
    out = GaussianMixture(
        jnp.zeros(C, gm.weights.dtype).at[dest].set(w.reshape(K * M), mode="drop"),
        jnp.zeros((C, d), gm.means.dtype).at[dest].set(m.reshape(K * M, d), mode="drop"),
        jnp.broadcast_to(eye, (C, d, d)).at[dest].set(P.reshape(K * M, d, d), mode="drop"),
        jnp.zeros(C, bool).at[dest].set(True, mode="drop"),
    )
    info = RefineInfo(
        n_split=jnp.sum(allowed.astype(jnp.int32)),
        n_out=jnp.sum(out.mask.astype(jnp.int32)),
        overflow=jnp.any(sel & ~allowed),
    )
    return sanitize(out), info
