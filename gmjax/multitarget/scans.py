"""Padded measurement sets: scans of any sizes in one ``(T, M, m)`` array whose NaN rows are absent.

The multi-target filters (:mod:`gmjax.multitarget.phd`, :mod:`gmjax.multitarget.cphd`) measure a padded
set ``(M, m)`` per step. :func:`measurement_mask` tells which rows of such a set are measurements, and
:func:`pad_scans` builds the padded array from a list of scans of different sizes, flagging in
:class:`PaddedScans` every scan that had more than ``M`` rows and was cut.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from gmjax._types import Array
from gmjax.multitarget.scenarios import bucket_capacity

__all__ = ["measurement_mask", "PaddedScans", "pad_scans"]


def measurement_mask(zs: Array) -> Array:
    """``(..., M)`` bool: which rows of a padded measurement set ``(..., M, m)`` are measurements (finite
    rows; a NaN row is an absent measurement, a row with an infinite entry is ignored and flagged)."""
    return jnp.all(jnp.isfinite(zs), axis=-1)


class PaddedScans(NamedTuple):
    """Measurement sets of any sizes in one padded array (the input of :func:`~gmjax.multitarget.phd.run`).

    Attributes:
        zs: ``(T, M, m)``, scan ``k``'s first ``min(n_k, M)`` measurements, then NaN rows.
        n_measurements: ``(T,)`` int32, ``n_k``, the measurements each scan had (before dropping).
        overflow: ``(T,)`` bool, the scan had more than ``M`` measurements: its rows past ``M`` were
            dropped and the filter never saw them.
    """

    zs: Array
    n_measurements: Array
    overflow: Array


def pad_scans(scans: Any, max_measurements: int | None = None, *, dtype: Any = None) -> PaddedScans:
    """Pad a list of measurement sets of different sizes to ``(T, M, m)``, flagging what does not fit.

    A padded array cannot show that its producer dropped rows: a scan of 40 returns cut to ``M = 32``
    rows looks like a scan of 32. Build the array here (as :func:`~gmjax.multitarget.simulate` does) so
    that every cut scan is flagged in ``overflow``; report or refuse those scans, or pass a larger
    ``max_measurements``. Rows are kept in the order given. Without ``max_measurements`` the capacity is
    the :func:`~gmjax.multitarget.bucket_capacity` of the largest scan (nothing is cut, and data sets of
    similar sizes share a capacity, so a filter compiled for one runs the others).

    Args:
        scans: a sequence of ``T`` arrays ``(n_k, m)`` (``n_k`` may be 0: an empty scan, shape
            ``(0, m)`` or ``[]``), concrete values of finite numbers.
        max_measurements: ``M >= 1``, the rows of each padded scan; ``None``: the power-of-two bucket
            of the largest scan.
        dtype: floating dtype of ``zs`` (default: the JAX default float).

    Returns:
        A :class:`PaddedScans`.

    Raises:
        ValueError: naming the scan: not a ``(n, m)`` array, ``m`` not that of the other scans, a
            NaN or infinite entry (NaN marks an absent row in the padded form), or ``max_measurements``
            not a positive int.
    """
    if max_measurements is not None and (
        isinstance(max_measurements, bool) or not isinstance(max_measurements, (int, np.integer))
    ):
        raise ValueError(f"max_measurements: expected a positive int or None, got {max_measurements!r}")
    if max_measurements is not None and int(max_measurements) < 1:
        raise ValueError(f"max_measurements: expected a positive int, got {max_measurements}")
    arrays = [np.asarray(z, dtype=np.float64) for z in scans]
    if not arrays:
        raise ValueError("scans: expected at least one scan")
    largest = max(a.shape[0] if a.ndim == 2 else 0 for a in arrays)
    M = bucket_capacity(largest) if max_measurements is None else int(max_measurements)
    dims = {a.shape[1] for a in arrays if a.ndim == 2 and a.shape[0] > 0}
    if len(dims) > 1:
        raise ValueError(f"scans: the scans' measurements differ in dimension m: {sorted(dims)}")
    if not dims:
        raise ValueError("scans: every scan is empty, so the measurement dimension m is unknown")
    (m,) = dims
    zs = np.full((len(arrays), M, m), np.nan)
    counts = np.zeros(len(arrays), np.int32)
    for k, a in enumerate(arrays):
        if a.size == 0:
            continue
        if a.ndim != 2 or a.shape[1] != m:
            raise ValueError(f"scans[{k}]: expected shape (n, {m}), got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(
                f"scans[{k}]: holds a NaN or infinite entry (row {int(np.argwhere(~np.isfinite(a))[0, 0])}); "
                "NaN marks an absent row in the padded form, so leave absent measurements out"
            )
        counts[k] = a.shape[0]
        zs[k, : min(a.shape[0], M)] = a[:M]
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    return PaddedScans(jnp.asarray(zs, dtype), jnp.asarray(counts), jnp.asarray(counts > M))
