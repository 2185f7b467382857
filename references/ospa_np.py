"""Brute-force NumPy/SciPy references for OSPA and GOSPA (rectangular ``linear_sum_assignment``).

Independent of :mod:`gmjax.multitarget.metrics` (which pads to a square matrix and runs its own
Hungarian algorithm): here the assignment is SciPy's on the rectangular real-to-real matrix, and the
definitions are applied literally.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment


def _dist(x, y):
    return np.sqrt(np.sum((np.asarray(x)[:, None, :] - np.asarray(y)[None, :, :]) ** 2, axis=-1))


def ospa_ref(x, y, *, c: float, p: float) -> float:
    """OSPA (Schuhmacher et al. 2008, eq 3) between point sets ``x (n_x, d)`` and ``y (n_y, d)``."""
    x = np.asarray(x, float).reshape(-1, np.shape(x)[-1])
    y = np.asarray(y, float).reshape(-1, np.shape(y)[-1])
    m, n = len(x), len(y)
    if m == 0 and n == 0:
        return 0.0
    if m > n:
        x, y, m, n = y, x, n, m
    if m == 0:
        return float(c)
    D = np.minimum(_dist(x, y), c) ** p
    r, k = linear_sum_assignment(D)
    total = D[r, k].sum() + c**p * (n - m)
    return float((total / n) ** (1.0 / p))


def gospa_ref(x, y, *, c: float, p: float) -> dict:
    """GOSPA with ``alpha = 2`` (Rahmathullah et al. 2017) of estimates ``x`` against truth ``y``.

    Returns ``{"distance", "localisation", "missed", "false"}`` (the last three sum to distance^p).
    """
    x = np.asarray(x, float).reshape(-1, np.shape(x)[-1])
    y = np.asarray(y, float).reshape(-1, np.shape(y)[-1])
    half = c**p / 2.0
    if len(x) == 0 or len(y) == 0:
        missed, false = half * len(y), half * len(x)
        return {
            "distance": (missed + false) ** (1.0 / p),
            "localisation": 0.0,
            "missed": missed,
            "false": false,
        }
    d = _dist(x, y)
    D = np.minimum(d, c) ** p
    r, k = linear_sum_assignment(D)
    good = d[r, k] < c
    loc = float(np.sum(d[r, k][good] ** p))
    n_pairs = int(np.sum(good))
    missed = half * (len(y) - n_pairs)
    false = half * (len(x) - n_pairs)
    return {
        "distance": (loc + missed + false) ** (1.0 / p),
        "localisation": loc,
        "missed": missed,
        "false": false,
    }
