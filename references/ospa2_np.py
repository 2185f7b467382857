"""Brute-force OSPA^(2) track metric (Beard, Vo & Vo 2020), for small cases only.

M. Beard, B.-T. Vo, B.-N. Vo, "A solution for large-scale multi-object tracking", IEEE Trans. Signal
Processing 68, 2754–2769, 2020: OSPA^(2) is the OSPA (Schuhmacher, Vo & Vo 2008) between two sets of
tracks whose base distance is the time-averaged cut-off distance between two tracks, here evaluated
over a sliding window of scans with uniform weights (as the authors' ``compute_ospa2`` code does).

Independent of :mod:`gmjax.multitarget.tracks`: tracks are dicts ``{scan: position}`` built with plain
loops, the base distance is an explicit loop over scans, and the minimum over assignments enumerates
every injective map of the smaller set of tracks into the larger (``itertools.permutations``) instead
of a Hungarian algorithm, so it is exponential in the number of tracks.
"""

from __future__ import annotations

import itertools
import math

import numpy as np


def _tracks(truth_states, truth_alive, est_states, est_labels, est_mask, position_dims):
    """Truth tracks (a list) and estimated tracks (a dict by label), each a dict ``{scan: position}``."""
    K = len(truth_states)
    truth = []
    for n in range(len(truth_states[0]) if K else 0):
        track = {}
        for k in range(K):
            if truth_alive[k][n]:
                track[k] = np.array([float(truth_states[k][n][i]) for i in position_dims])
        truth.append(track)
    est = {}
    for k in range(K):
        for e in range(len(est_states[k])):
            if not est_mask[k][e]:
                continue
            label = (int(est_labels[k][e][0]), int(est_labels[k][e][1]))
            track = est.setdefault(label, {})
            if k in track:
                raise ValueError(f"label {label} present twice at scan {k}")
            track[k] = np.array([float(est_states[k][e][i]) for i in position_dims])
    return truth, est


def track_distance_ref(x: dict, y: dict, *, c: float, p: float) -> float:
    """Base distance between two tracks ``{scan: position}``: the order-``p`` mean over the scans where
    either exists of ``min(c, ||x_t - y_t||)`` (both exist) or ``c`` (one exists); 0 if neither ever does."""
    scans = sorted(set(x) | set(y))
    if not scans:
        return 0.0
    total = 0.0
    for t in scans:
        if t in x and t in y:
            dt = min(c, math.sqrt(sum((a - b) ** 2 for a, b in zip(x[t], y[t]))))
        else:
            dt = c
        total += dt**p
    return (total / len(scans)) ** (1.0 / p)


def ospa_tracks_ref(xs: list, ys: list, *, c: float, p: float) -> float:
    """OSPA of order ``p``, cut-off ``c`` between two lists of tracks, every assignment enumerated."""
    if len(xs) > len(ys):
        xs, ys = ys, xs
    m, n = len(xs), len(ys)
    if n == 0:
        return 0.0
    best = math.inf
    for perm in itertools.permutations(range(n), m):
        cost = sum(min(c, track_distance_ref(xs[i], ys[perm[i]], c=c, p=p)) ** p for i in range(m))
        best = min(best, cost)
    return ((best + c**p * (n - m)) / n) ** (1.0 / p)


def ospa2_ref(
    truth_states,
    truth_alive,
    est_states,
    est_labels,
    est_mask,
    *,
    c: float,
    p: float,
    window: int,
    position_dims=(0, 1),
) -> np.ndarray:
    """OSPA^(2) at each scan ``k`` over the window ``[max(0, k - window + 1), k]``.

    Args:
        truth_states: ``(K, N, d)``; truth_alive: ``(K, N)``; target ``n`` is one track.
        est_states: ``(K, E, d)``; est_labels: ``(K, E, 2)``; est_mask: ``(K, E)``; a label is one track.
        c: cut-off; p: order; window: number of scans; position_dims: the position coordinates.

    Returns:
        ``(K,)`` OSPA^(2) values.
    """
    truth, est = _tracks(truth_states, truth_alive, est_states, est_labels, est_mask, position_dims)
    K = len(truth_states)
    out = []
    for k in range(K):
        scans = range(max(0, k - window + 1), k + 1)
        xs = [{t: track[t] for t in scans if t in track} for track in truth]
        ys = [{t: track[t] for t in scans if t in track} for track in est.values()]
        xs = [x for x in xs if x]
        ys = [y for y in ys if y]
        out.append(ospa_tracks_ref(xs, ys, c=c, p=p))
    return np.array(out)
