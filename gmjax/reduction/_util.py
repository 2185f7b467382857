"""Private helpers shared by the reducers: eager validation, small-matrix algebra, finalisation.

The small-matrix helpers (:func:`logdet`, :func:`inv_quad`, :func:`inv`) specialise ``d = 1`` and
``d = 2`` to closed forms (the static benchmark and the PCRB coarsening are 1-D and 2-D and evaluate
them ``K^2`` or ``K * num_out`` times per step); larger ``d`` goes through a Cholesky factor.
"""

from __future__ import annotations

import functools
import inspect
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import mixture
from gmjax.mixture import GaussianMixture

_LOG_2PI = 1.8378770664093453


# ----------------------------------------------------------------------------- eager validation


def is_concrete(*xs: Any) -> bool:
    """True when none of the leaves of ``xs`` is a tracer (we are at the eager API boundary)."""
    leaves = jax.tree_util.tree_leaves(xs)
    return not any(isinstance(x, jax.core.Tracer) for x in leaves)


def validate_mixture(gm: GaussianMixture, name: str = "gm") -> None:
    """Raise ``ValueError`` for a bad concrete mixture (no-op on tracers).

    A vectorised fast path checks finiteness, signs, symmetry and positive definiteness of the live
    covariances at once; on any failure :func:`gmjax.mixture.check` produces the named message.
    """
    if not isinstance(gm, GaussianMixture):
        raise ValueError(f"{name}: expected a GaussianMixture, got {type(gm).__name__}")
    if not is_concrete(gm):
        return
    try:
        w, m, P, mask = (np.asarray(a) for a in gm)
        ok = (
            w.ndim == 1
            and m.ndim == 2
            and P.ndim == 3
            and mask.dtype == np.bool_
            and mask.shape == w.shape
            and m.shape[0] == w.shape[0]
            and P.shape == (w.shape[0], m.shape[1], m.shape[1])
        )
        if ok:
            ok = bool(
                np.isfinite(w).all()
                and np.isfinite(m).all()
                and np.isfinite(P).all()
                and (w >= 0).all()
                and mask.any()
                and (w[mask] > 0).any()
            )
        if ok:
            Pl = P[mask].astype(np.float64)
            scale = np.maximum(np.abs(Pl).max(axis=(1, 2)), 1e-300)[:, None, None]
            ok = bool(np.all(np.abs(Pl - np.swapaxes(Pl, 1, 2)) <= 1e-8 * scale + 1e-10 * scale))
            if ok:
                np.linalg.cholesky(Pl)
            pad = ~mask
            if ok and pad.any():
                d = m.shape[1]
                ok = bool(
                    (w[pad] == 0).all() and (m[pad] == 0).all() and (P[pad] == np.eye(d)).all()
                )
    except np.linalg.LinAlgError:
        ok = False
    if not ok:
        try:
            mixture.check(gm)
        except ValueError as err:
            raise ValueError(f"{name}: {err}") from None
        # check() accepted what the fast path rejected (tolerance corner): accept it as well.


def validate_count(value: Any, name: str, low: int, high: int) -> int:
    """A static integer in ``[low, high]`` or a ``ValueError`` naming ``name``."""
    if isinstance(value, jax.core.Tracer):
        raise ValueError(f"{name}: must be a static Python int (it fixes an array size), got a tracer")
    try:
        iv = int(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected an integer, got {value!r}") from None
    if iv != value:
        raise ValueError(f"{name}: expected an integer, got {value!r}")
    if iv < low or iv > high:
        raise ValueError(f"{name}: must be in [{low}, {high}], got {iv}")
    return iv


def validate_capacity(capacity: Any, gm: GaussianMixture, minimum: int = 1) -> int:
    """Resolve the output capacity (default: the input's) and check it is ``>= minimum``."""
    if capacity is None:
        capacity = gm.capacity
    if isinstance(capacity, jax.core.Tracer):
        raise ValueError("capacity: must be a static Python int")
    cap = int(capacity)
    if cap != capacity or cap < max(minimum, 1):
        raise ValueError(f"capacity: must be an integer >= {max(minimum, 1)}, got {capacity!r}")
    return cap


def validate_nonneg(value: Any, name: str, *, allow_inf: bool = True) -> None:
    """``ValueError`` when a concrete threshold is negative or NaN (no-op on tracers)."""
    if value is None or not is_concrete(value):
        return
    arr = np.asarray(value, dtype=np.float64)
    if np.isnan(arr).any():
        raise ValueError(f"{name}: must not be NaN, got {value!r}")
    if (arr < 0).any():
        raise ValueError(f"{name}: must be non-negative, got {value!r}")
    if not allow_inf and np.isinf(arr).any():
        raise ValueError(f"{name}: must be finite, got {value!r}")


def validate_count_threshold(
    gm: GaussianMixture, num_out: Any, threshold: Any, capacity: Any
) -> tuple[int, jax.Array, int]:
    """Validate the arguments of a count-and-threshold reducer (Runnalls, Salmond, West, Williams,
    COWA): ``(num_out, threshold as an array of the mixture's dtype (None -> inf), capacity)``."""
    validate_mixture(gm)
    num_out = validate_count(num_out, "num_out", 1, gm.capacity)
    cap = validate_capacity(capacity, gm, minimum=num_out)
    validate_nonneg(threshold, "threshold")
    threshold = jnp.asarray(jnp.inf if threshold is None else threshold, gm.weights.dtype)
    return num_out, threshold, cap


def validate_range(value: Any, name: str, low: float, high: float) -> None:
    """``ValueError`` when a concrete value lies outside ``[low, high]``."""
    if value is None or not is_concrete(value):
        return
    arr = np.asarray(value, dtype=np.float64)
    if np.isnan(arr).any() or (arr < low).any() or (arr > high).any():
        raise ValueError(f"{name}: must be in [{low}, {high}], got {value!r}")


# ----------------------------------------------------------------------------- small-matrix algebra


def logdet(P: jax.Array) -> jax.Array:
    """``log det P`` for ``(..., d, d)`` SPD matrices (closed form for d <= 2)."""
    d = P.shape[-1]
    if d == 1:
        return jnp.log(P[..., 0, 0])
    if d == 2:
        return jnp.log(P[..., 0, 0] * P[..., 1, 1] - P[..., 0, 1] * P[..., 1, 0])
    L = jnp.linalg.cholesky(P)
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), axis=-1)


def inv(P: jax.Array) -> jax.Array:
    """Inverse of ``(..., d, d)`` SPD matrices (closed form for d <= 2), symmetrised."""
    d = P.shape[-1]
    if d == 1:
        return 1.0 / P
    if d == 2:
        a, b, c, e = P[..., 0, 0], P[..., 0, 1], P[..., 1, 0], P[..., 1, 1]
        det = a * e - b * c
        out = jnp.stack([jnp.stack([e, -b], -1), jnp.stack([-c, a], -1)], -2) / det[..., None, None]
        return 0.5 * (out + jnp.swapaxes(out, -1, -2))
    L = jnp.linalg.cholesky(P)
    eye = jnp.broadcast_to(jnp.eye(d, dtype=P.dtype), P.shape)
    Linv = jax.scipy.linalg.solve_triangular(L, eye, lower=True)
    return jnp.swapaxes(Linv, -1, -2) @ Linv


def inv_quad(x: jax.Array, P: jax.Array) -> jax.Array:
    """``x^T P^{-1} x`` for ``x`` ``(..., d)`` and SPD ``P`` ``(..., d, d)``."""
    d = P.shape[-1]
    if d == 1:
        return x[..., 0] ** 2 / P[..., 0, 0]
    if d == 2:
        a, b, e = P[..., 0, 0], P[..., 0, 1], P[..., 1, 1]
        det = a * e - b * b
        x0, x1 = x[..., 0], x[..., 1]
        return (e * x0 * x0 - 2.0 * b * x0 * x1 + a * x1 * x1) / det
    L = jnp.linalg.cholesky(P)
    r = jax.scipy.linalg.solve_triangular(L, x[..., None], lower=True)[..., 0]
    return jnp.sum(r * r, axis=-1)


def log_gauss(x: jax.Array, m: jax.Array, P: jax.Array) -> jax.Array:
    """``log N(x; m, P)`` broadcast over leading axes."""
    d = P.shape[-1]
    return -0.5 * (d * _LOG_2PI + logdet(P) + inv_quad(x - m, P))


def kl_gauss(m1, P1, m2, P2) -> jax.Array:
    """``KL(N(m1, P1) || N(m2, P2))`` broadcast over leading axes."""
    d = P1.shape[-1]
    P2i = inv(P2)
    tr = jnp.sum(P2i * P1, axis=(-1, -2))
    return 0.5 * (tr + inv_quad(m2 - m1, P2) - d + logdet(P2) - logdet(P1))


def merge_pair(w1, m1, P1, w2, m2, P2):
    """Moment-preserving merge of two components (seed 002 eqs 70–72 written with ``lambda_i``).

    ``W = w1 + w2``, ``l_i = w_i / W``, ``m = l1 m1 + l2 m2``,
    ``P = l1 P1 + l2 P2 + l1 l2 (m1 - m2)(m1 - m2)^T``. A pair of zero weights gives equal ``l_i``.
    """
    W = w1 + w2
    ok = W > 0
    Ws = jnp.where(ok, W, 1.0)
    l1 = jnp.where(ok, w1 / Ws, 0.5)
    l2 = jnp.where(ok, w2 / Ws, 0.5)
    diff = m1 - m2
    m = l1 * m1 + l2 * m2
    P = l1 * P1 + l2 * P2 + (l1 * l2) * jnp.outer(diff, diff)
    return W, m, 0.5 * (P + P.T)


# ----------------------------------------------------------------------------- finalisation


def finalize(
    gm_in: GaussianMixture,
    work: GaussianMixture,
    labels: jax.Array,
    capacity: int,
):
    """Compact a working mixture (capacity ``K_w``) into ``capacity`` output slots.

    Live slots keep their relative order; if more than ``capacity`` are live, the heaviest are kept
    (``overflow``) and their weights are *not* renormalised (the dropped weight is ``dropped``).

    Args:
        gm_in: the reducer's input (only used for shapes).
        work: the working mixture; its ``mask`` says which slots are live.
        labels: ``(K_in,)`` working slot of every input slot, ``-1`` for none.
        capacity: static output capacity.

    Returns:
        ``(gm_out, labels_out, overflow, dropped_mass)``.
    """
    del gm_in
    Kw = work.capacity
    n_live = jnp.sum(work.mask.astype(jnp.int32))
    overflow = n_live > capacity
    if capacity >= Kw:
        out = mixture.pad(work, capacity) if capacity > Kw else work
        order = jnp.argsort(~out.mask, stable=True)
        out = jax.tree_util.tree_map(lambda a: a[order], out)
        pos = jnp.zeros(capacity, jnp.int32).at[order].set(jnp.arange(capacity, dtype=jnp.int32))
        labels_out = jnp.where(labels >= 0, pos[jnp.maximum(labels, 0)], -1)
        return mixture.sanitize(out), labels_out, jnp.asarray(False), jnp.zeros((), work.weights.dtype)
    order_keep = jnp.argsort(~work.mask, stable=True)[:capacity]
    _, order_top = jax.lax.top_k(jnp.where(work.mask, work.weights, -jnp.inf), capacity)
    idx = jnp.where(overflow, order_top, order_keep)
    out = jax.tree_util.tree_map(lambda a: a[idx], work)
    valid = work.mask[idx]
    out = mixture.sanitize(out._replace(mask=valid))
    pos = jnp.full(Kw, -1, jnp.int32).at[idx].max(
        jnp.where(valid, jnp.arange(capacity, dtype=jnp.int32), -1)
    )
    labels_out = jnp.where(labels >= 0, pos[jnp.maximum(labels, 0)], -1)
    kept = jnp.zeros(Kw, bool).at[idx].set(valid)
    dropped = jnp.sum(jnp.where(work.mask & ~kept, work.weights, 0.0))
    return out, labels_out, overflow, dropped


def identity_labels(gm: GaussianMixture) -> jax.Array:
    """``(K,)`` labels mapping every live slot to itself and padded slots to ``-1``."""
    return jnp.where(gm.mask, jnp.arange(gm.capacity, dtype=jnp.int32), -1)


def l2_inner(a: GaussianMixture, b: GaussianMixture) -> jax.Array:
    """``∫ f_a f_b dx = sum_ij w_i w_j N(m_i; m_j, P_i + P_j)`` with the closed-form small-matrix
    helpers (cheaper to compile than :mod:`gmjax.metrics`, which goes through ``safe_cholesky``)."""
    wa = jnp.where(a.mask, a.weights, 0.0)
    wb = jnp.where(b.mask, b.weights, 0.0)
    eye = jnp.eye(a.dim, dtype=a.covs.dtype)
    Pa = jnp.where(a.mask[:, None, None], a.covs, eye)
    Pb = jnp.where(b.mask[:, None, None], b.covs, eye)
    S = jnp.exp(log_gauss(a.means[:, None], b.means[None], Pa[:, None] + Pb[None]))
    S = jnp.where(a.mask[:, None] & b.mask[None, :], S, 0.0)
    return wa @ S @ wb


def ise(a: GaussianMixture, b: GaussianMixture) -> jax.Array:
    """Closed-form ISE (seed 000 eqs 31, 35), clipped at 0; equals :func:`gmjax.metrics.ise`."""
    return jnp.maximum(l2_inner(a, a) - 2.0 * l2_inner(a, b) + l2_inner(b, b), 0.0)


# ----------------------------------------------------------------------------- NaN thresholds


def _traced_float(x: Any) -> bool:
    return isinstance(x, jax.core.Tracer) and jnp.issubdtype(x.dtype, jnp.inexact)


def unchanged(gm: GaussianMixture, capacity: int):
    """The "no reduction" result: ``gm`` fitted to ``capacity`` slots by :func:`finalize`.

    Returns:
        ``(gm_out, labels, overflow, dropped_mass)``.
    """
    return finalize(gm, gm, identity_labels(gm), capacity)


def select_unchanged(bad: jax.Array, gm: GaussianMixture, out: GaussianMixture, info: Any):
    """``(out, info)`` where ``bad`` is False; else the input unchanged (see :func:`unchanged`)
    with ``cost = 0``; ``info.invalid_threshold = bad`` either way."""
    same, labels, overflow, dropped = unchanged(gm, out.capacity)
    pick = functools.partial(jnp.where, bad)
    out = jax.tree_util.tree_map(pick, same, out)
    info = info._replace(
        n_out=pick(jnp.sum(same.mask.astype(jnp.int32)), info.n_out),
        pruned_mass=pick(dropped.astype(info.pruned_mass.dtype), info.pruned_mass),
        labels=pick(labels, info.labels),
        overflow=pick(overflow, info.overflow),
        cost=pick(jnp.zeros_like(info.cost), info.cost),
        invalid_threshold=jnp.asarray(bad, bool) | jnp.asarray(info.invalid_threshold, bool),
    )
    return out, info


def guard_nan(**safe: Any) -> Callable:
    """Decorate a public reducer ``f(gm, ...) -> (out, info)`` (or ``(out, state, info)``) so a
    *traced* NaN in any of the named arguments gives a defined, flagged result.

    ``safe`` maps argument names to a valid stand-in. When any traced floating leaf of those
    arguments is NaN, the reducer runs on the stand-ins (so no NaN reaches its arithmetic or its
    gradients) and its result is replaced by the input unchanged (:func:`select_unchanged`), with
    ``info.invalid_threshold`` set; a stateful reducer's new state is then a fresh one
    (``state_init(capacity)``, passed as ``safe["state_init"]``). Concrete NaNs are left to the
    reducer's eager validation (a ``ValueError``).
    """
    state_init = safe.pop("state_init", None)

    def deco(fn: Callable) -> Callable:
        sig = inspect.signature(fn)
        first = next(iter(sig.parameters))

        @functools.wraps(fn)
        def wrapped(*args, **kwargs):
            bound = sig.bind(*args, **kwargs)
            bound.apply_defaults()
            bad = None
            for name, stand_in in safe.items():
                value = bound.arguments.get(name)
                leaves = jax.tree_util.tree_leaves(value)
                if not any(_traced_float(x) for x in leaves):
                    continue

                def clean(x, stand_in=stand_in):
                    nonlocal bad
                    if not _traced_float(x):
                        return x
                    nan = jnp.any(jnp.isnan(x))
                    bad = nan if bad is None else bad | nan
                    return jnp.where(jnp.isnan(x), jnp.asarray(stand_in, x.dtype), x)

                bound.arguments[name] = jax.tree_util.tree_map(clean, value)
            result = fn(*bound.args, **bound.kwargs)
            if bad is None:
                return result
            gm = bound.arguments[first]
            if len(result) == 3:
                out, state, info = result
                out, info = select_unchanged(bad, gm, out, info)
                fresh = state_init(out.capacity)
                state = jax.tree_util.tree_map(functools.partial(jnp.where, bad), fresh, state)
                return out, state, info
            return select_unchanged(bad, gm, *result)

        return wrapped

    return deco
