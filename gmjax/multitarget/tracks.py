"""Track metrics on the host: how well labelled multi-target estimates follow the true tracks.

Two measures of a labelled filter's output (per scan ``k = 0 .. K-1``: estimates ``states (K, E, d)``,
``labels (K, E, 2)``, ``mask (K, E)``) against the ground truth of
:func:`gmjax.multitarget.scenarios.simulate` (``states (K, N, d)``, ``alive (K, N)``; target ``n`` is
one track):

* :func:`ospa2`, the OSPA^(2) track metric of Beard, Vo & Vo (2020), over a sliding window of scans:
  it sees track identity, so it penalises a label swap even where every scan's positions are right;
* :func:`label_switches`, the gated ID-switch count of tracking benchmarks (and fragmentations).

A track of the estimates is the set of rows that carry one label ``(birth step, birth slot)``
(``(-1, -1)`` marks an empty slot and may not be present); a label is present at most once per scan.
Both metrics use positions only: ``position_dims`` (default ``(0, 1)``) picks the coordinates of the
state vectors, and distances are Euclidean.

These are NumPy/SciPy functions run on concrete arrays (JAX arrays are converted with
``np.asarray``): they are **not** jit-able, vmap-able or differentiable. For per-scan set metrics
that are, see :mod:`gmjax.multitarget.metrics`.

Reference: M. Beard, B.-T. Vo, B.-N. Vo, "A solution for large-scale multi-object tracking", IEEE
Trans. Signal Processing 68, 2754–2769, 2020 (its section on the OSPA^(2) metric); the window and the
time-averaged base distance follow the authors' ``compute_ospa2`` code.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import linear_sum_assignment

__all__ = ["LabelSwitches", "label_switches", "ospa2"]


class _Tracks(NamedTuple):
    """Validated inputs rearranged as tracks (positions 0 where a track does not exist)."""

    truth: np.ndarray  # (K, N, q) float64
    truth_exists: np.ndarray  # (K, N) bool
    labels: np.ndarray  # (L, 2) int64, the distinct labels present, sorted
    est: np.ndarray  # (K, L, q) float64
    est_exists: np.ndarray  # (K, L) bool


def _positive_real(value: Any, name: str, *, allow_inf: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a real number > 0, got {value!r}") from None
    if isinstance(value, (bool, np.bool_)) or math.isnan(v) or v <= 0 or (math.isinf(v) and not allow_inf):
        finite = "" if allow_inf else " finite"
        raise ValueError(f"{name}: expected a{finite} real number > 0, got {value!r}")
    return v


def _mask(value: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    m = np.asarray(value)
    if m.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {m.shape}")
    if m.dtype != bool:
        if not np.issubdtype(m.dtype, np.integer) or not np.isin(m, (0, 1)).all():
            raise ValueError(f"{name}: expected booleans (or integers 0/1), got dtype {m.dtype}")
        m = m.astype(bool)
    return m


def _position_dims(position_dims: Sequence[int], d: int) -> list[int]:
    try:
        dims = [int(i) for i in position_dims]
    except (TypeError, ValueError):
        raise ValueError(f"position_dims: expected a sequence of ints, got {position_dims!r}") from None
    if not dims:
        raise ValueError("position_dims: expected at least one coordinate, got none")
    if any(not -d <= i < d for i in dims):
        raise ValueError(f"position_dims: {tuple(dims)} out of range for states of dimension d = {d}")
    dims = [i % d for i in dims]
    if len(set(dims)) != len(dims):
        raise ValueError(f"position_dims: repeated coordinates in {tuple(position_dims)}")
    return dims


def _tracks(
    truth_states: ArrayLike,
    truth_alive: ArrayLike,
    est_states: ArrayLike,
    est_labels: ArrayLike,
    est_mask: ArrayLike,
    position_dims: Sequence[int],
) -> _Tracks:
    xs = np.asarray(truth_states, dtype=float)
    if xs.ndim != 3:
        raise ValueError(f"truth_states: expected shape (K, N, d), got {xs.shape}")
    K, N, d = xs.shape
    alive = _mask(truth_alive, (K, N), "truth_alive")
    ys = np.asarray(est_states, dtype=float)
    if ys.ndim != 3:
        raise ValueError(f"est_states: expected shape (K, E, d), got {ys.shape}")
    if ys.shape[0] != K:
        raise ValueError(f"est_states: expected K = {K} scans (as truth_states), got {ys.shape[0]}")
    if ys.shape[2] != d:
        raise ValueError(f"est_states: expected state dimension d = {d} (as truth_states), got {ys.shape[2]}")
    E = ys.shape[1]
    labels = np.asarray(est_labels)
    if labels.shape != (K, E, 2):
        raise ValueError(f"est_labels: expected shape {(K, E, 2)}, got {labels.shape}")
    if not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(
            f"est_labels: expected integer labels (birth step, birth slot), got dtype {labels.dtype}"
        )
    present = _mask(est_mask, (K, E), "est_mask")
    dims = _position_dims(position_dims, d)

    x = xs[..., dims]
    if not np.isfinite(x[alive]).all():
        k = int(np.nonzero(~np.isfinite(x).all(-1) & alive)[0][0])
        raise ValueError(f"truth_states: non-finite position of a live target at scan {k}")
    y = ys[..., dims]
    if not np.isfinite(y[present]).all():
        k = int(np.nonzero(~np.isfinite(y).all(-1) & present)[0][0])
        raise ValueError(f"est_states: non-finite position of a present estimate at scan {k}")

    ks, es = np.nonzero(present)
    labs = labels[ks, es].astype(np.int64)  # (M, 2)
    empty = (labs == -1).all(-1)
    if empty.any():
        i = int(np.argmax(empty))
        raise ValueError(
            f"est_labels: the estimate in slot {int(es[i])} at scan {int(ks[i])} is present (est_mask) "
            "but carries the empty label (-1, -1)"
        )
    uniq, inv = np.unique(labs.reshape(-1, 2), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    L = len(uniq)
    _, first, counts = np.unique(ks * L + inv, return_index=True, return_counts=True)
    if (counts > 1).any():
        i = first[int(np.argmax(counts > 1))]
        raise ValueError(
            f"est_labels: label {tuple(int(v) for v in labs[i])} is present more than once at scan "
            f"{int(ks[i])} (a label is one track: at most one estimate per scan)"
        )
    est = np.zeros((K, L, len(dims)))
    est[ks, inv] = y[ks, es]
    est_exists = np.zeros((K, L), bool)
    est_exists[ks, inv] = True
    truth = np.where(alive[..., None], x, 0.0)
    return _Tracks(truth, alive, uniq.reshape(L, 2), est, est_exists)


def ospa2(
    truth_states: ArrayLike,
    truth_alive: ArrayLike,
    est_states: ArrayLike,
    est_labels: ArrayLike,
    est_mask: ArrayLike,
    *,
    cutoff: float = 100.0,
    order: float = 1,
    window: int = 10,
    position_dims: Sequence[int] = (0, 1),
) -> np.ndarray:
    """OSPA^(2) between the true and the estimated tracks, over a sliding window of scans.

    At scan ``k`` the window is ``W = [max(0, k - window + 1), k]``. The tracks in it are every true
    target ``n`` (its positions at the scans of ``W`` where it is alive) and every estimated label (its
    positions at the scans of ``W`` where it is present); only tracks that exist at some scan of ``W``
    count. With ``c = cutoff`` and ``p = order``, the base distance between tracks ``X`` and ``Y`` is

        ``d(X, Y) = (sum_{t in D} d_c(X_t, Y_t)^p / |D|)^(1/p)``,  ``D`` = scans of ``W`` where ``X``
        or ``Y`` exists,

    with ``d_c = min(c, ||X_t - Y_t||)`` when both exist and ``d_c = c`` when one does (``d = 0`` for
    ``D`` empty; it never is for counted tracks). OSPA^(2) is the OSPA of order ``p`` and cut-off ``c``
    between the ``n_x`` true and ``n_y`` estimated tracks with ``d`` as the base distance
    (``d <= c`` already):

        ``((min_pi sum_i d(X_i, Y_pi(i))^p + c^p |n_x - n_y|) / max(n_x, n_y))^(1/p)``,

    ``0`` when both sets are empty (Beard, Vo & Vo 2020, with uniform time weights). The
    minimum is over injective assignments of the smaller set into the larger, solved by
    ``scipy.optimize.linear_sum_assignment`` on the rectangular matrix of ``d^p``. Because a label is
    one track, an estimate that follows the right positions under the wrong label costs as much as a
    wrong position: a label swap raises OSPA^(2) while the per-scan OSPA stays 0.

    Host-side NumPy/SciPy: not jit-able, not differentiable.

    Args:
        truth_states: ``(K, N, d)`` true states (any value where not alive).
        truth_alive: ``(K, N)`` bool, target ``n`` alive at scan ``k``.
        est_states: ``(K, E, d)`` estimated states (any value where absent).
        est_labels: ``(K, E, 2)`` int, the label ``(birth step, birth slot)`` of each estimate
            (``(-1, -1)`` for empty slots; ignored where ``est_mask`` is False).
        est_mask: ``(K, E)`` bool, which estimates are present.
        cutoff: ``c > 0``, finite.
        order: ``p >= 1``, finite.
        window: number of scans ``>= 1`` in the window (``window >= K`` means from scan 0 on).
        position_dims: the coordinates of the state vector that are positions.

    Returns:
        ``(K,)`` float64, OSPA^(2) at each scan, in ``[0, c]``.

    Raises:
        ValueError: shapes that disagree (``K``, ``E``, ``d``), non-integer labels, a present estimate
            with the empty label or a label present twice in one scan (the message names the scan),
            non-finite positions of live targets or present estimates, ``cutoff <= 0``, ``order < 1``,
            ``window < 1``, or ``position_dims`` out of range.
    """
    c = _positive_real(cutoff, "cutoff")
    p = _positive_real(order, "order")
    if p < 1:
        raise ValueError(f"order: expected a real number >= 1, got {order!r}")
    if isinstance(window, (bool, np.bool_)) or not isinstance(window, (int, np.integer)) or window < 1:
        raise ValueError(f"window: expected an integer >= 1, got {window!r}")
    tr = _tracks(truth_states, truth_alive, est_states, est_labels, est_mask, position_dims)
    K, N = tr.truth_exists.shape
    L = tr.est_exists.shape[1]
    cp = c**p

    # per scan: d_c^p between every true track and every label track, and whether either exists
    dcp = np.zeros((K, N, L))
    either = np.zeros((K, N, L), np.int64)
    for k in range(K):
        both = tr.truth_exists[k][:, None] & tr.est_exists[k][None, :]
        one = tr.truth_exists[k][:, None] ^ tr.est_exists[k][None, :]
        dist = np.linalg.norm(tr.truth[k][:, None, :] - tr.est[k][None, :, :], axis=-1)
        dcp[k] = np.where(both, np.minimum(dist, c) ** p, np.where(one, cp, 0.0))
        either[k] = both | one

    out = np.zeros(K)
    for k in range(K):
        win = slice(max(0, k - int(window) + 1), k + 1)
        rows = tr.truth_exists[win].any(0)
        cols = tr.est_exists[win].any(0)
        m, n = int(rows.sum()), int(cols.sum())
        if m == 0 and n == 0:
            continue
        total = cp * abs(m - n)
        if m and n:
            sub = np.ix_(rows, cols)
            # |D| >= 1 for every counted pair: one of the two tracks exists in the window
            cost = dcp[win].sum(0)[sub] / either[win].sum(0)[sub]  # d(X, Y)^p
            r, j = linear_sum_assignment(cost)
            total += float(cost[r, j].sum())
        out[k] = (total / max(m, n)) ** (1.0 / p)
    return out


class LabelSwitches(NamedTuple):
    """Label switches (ID switches) and fragmentations of the estimated tracks, per true target.

    Attributes:
        total: the number of switches over all targets and scans.
        per_target: ``(N,)`` int, the switches of each target.
        assigned: ``(K, N)`` int, the label each target is assigned to at each scan, as an index into
            ``labels``, or -1 (not alive, or no estimate within the gate).
        labels: ``(L, 2)`` int, the distinct labels present in the estimates (sorted).
        fragmentations: ``(N,)`` int, how often the tracking of each target resumes after an
            interruption (see :func:`label_switches`).
    """

    total: int
    per_target: np.ndarray
    assigned: np.ndarray
    labels: np.ndarray
    fragmentations: np.ndarray


def label_switches(
    truth_states: ArrayLike,
    truth_alive: ArrayLike,
    est_states: ArrayLike,
    est_labels: ArrayLike,
    est_mask: ArrayLike,
    *,
    gate: float = 100.0,
    position_dims: Sequence[int] = (0, 1),
) -> LabelSwitches:
    """Gated label switches (the "ID switches" of tracking benchmarks) of the estimates per true target.

    **Assignment.** At each scan ``k`` the live targets and the present estimates are matched by
    ``scipy.optimize.linear_sum_assignment`` on the Euclidean position distances truncated at the gate,
    ``min(||x - y||, gate)``, and the pairs with distance ``> gate`` are discarded. Truncating before
    the assignment (rather than discarding after an assignment on raw distances) means a far-away
    estimate never pulls a pair apart that lies within the gate: the matching minimises the sum of
    matched distances plus ``gate`` per live target left unmatched (the GOSPA assignment with
    ``p = 1``, ``c = gate``). The assignment is per scan, with no preference for the previous scan's
    pairs (unlike CLEAR MOT's correspondence carry-over).

    **Switch.** A switch is counted for target ``n`` at scan ``k`` when ``n`` is assigned a label at
    ``k`` and the label it was last assigned (at the last earlier scan at which it was assigned at all,
    however long ago) is a different label. The first assignment of a target is no switch, nor is a
    scan without an assignment.

    **Fragmentation.** One is counted for target ``n`` at scan ``k`` when ``n`` is assigned at ``k``,
    was assigned at some earlier scan, and was alive but unassigned at some scan in between (a scan
    where it is not alive is no interruption).

    Host-side NumPy/SciPy: not jit-able, not differentiable.

    Args:
        truth_states, truth_alive, est_states, est_labels, est_mask, position_dims: as in :func:`ospa2`.
        gate: the largest distance ``> 0`` at which a target and an estimate are matched (``inf``: no
            gate).

    Returns:
        :class:`LabelSwitches`.

    Raises:
        ValueError: invalid inputs as in :func:`ospa2`, or ``gate`` not ``> 0``.
    """
    g = _positive_real(gate, "gate", allow_inf=True)
    tr = _tracks(truth_states, truth_alive, est_states, est_labels, est_mask, position_dims)
    K, N = tr.truth_exists.shape
    assigned = np.full((K, N), -1, np.int64)
    for k in range(K):
        ti = np.nonzero(tr.truth_exists[k])[0]
        li = np.nonzero(tr.est_exists[k])[0]
        if len(ti) == 0 or len(li) == 0:
            continue
        dist = np.linalg.norm(tr.truth[k, ti][:, None, :] - tr.est[k, li][None, :, :], axis=-1)
        r, j = linear_sum_assignment(np.minimum(dist, g))
        keep = dist[r, j] <= g
        assigned[k, ti[r[keep]]] = li[j[keep]]

    per_target = np.zeros(N, np.int64)
    frags = np.zeros(N, np.int64)
    for n in range(N):
        last = -1  # the label last assigned
        interrupted = False
        for k in range(K):
            a = int(assigned[k, n])
            if a >= 0:
                if last >= 0:
                    per_target[n] += a != last
                    frags[n] += interrupted
                last, interrupted = a, False
            elif last >= 0 and tr.truth_exists[k, n]:
                interrupted = True
    return LabelSwitches(int(per_target.sum()), per_target, assigned, tr.labels, frags)
