"""Eager argument validation at the API boundary, shared by every package (no-ops on tracers)."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import mixture
from gmjax.mixture import GaussianMixture


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
                ok = bool((w[pad] == 0).all() and (m[pad] == 0).all() and (P[pad] == np.eye(d)).all())
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
