"""Streaming moments of a study: per-block shifted sums, their centring, Chan's pairwise merge in a
fixed binary tree over block indices, log-spaced histograms for medians, the ARMSE standard error."""

from __future__ import annotations

from typing import Any, NamedTuple, cast

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._types import Array
from gmjax.montecarlo.runs import SCORE_NAMES, RunScores

__all__ = ["StudyMoments", "BlockSums"]

HIST_NAMES = ("nees", "position_error")
HIST_LOG10_LOW, HIST_LOG10_HIGH, HIST_BINS_PER_DECADE = -10.0, 10.0, 1000
_N_BINS = int((HIST_LOG10_HIGH - HIST_LOG10_LOW) * HIST_BINS_PER_DECADE)
_HIST_SIZE = _N_BINS + 3  # [underflow (incl. 0), bins..., overflow, NaN]

# ----------------------------------------------------------------------------- streaming moments


class StudyMoments(NamedTuple):
    """Streaming sufficient statistics of a study (host NumPy: float64 / int64).

    Attributes:
        n: ``()`` runs accumulated.
        mean: ``(S, T)`` per-step mean of each score of :data:`SCORE_NAMES`.
        m2: ``(S, T)`` per-step centred sum of squares ``Σ_i (x_it - mean_t)²``.
        sq_cross: ``(T, T)`` centred cross-moments ``Σ_i (e_i - ē)(e_i - ē)^T`` of the squared error.
        position_sq_cross: ``(T, T)`` the same for the position squared error.
        hist: ``(2, bins + 3)`` counts of NEES and position error in log-spaced bins (see module doc).
        n_flagged_runs: ``()`` runs with at least one flagged step.
    """

    n: np.ndarray
    mean: np.ndarray
    m2: np.ndarray
    sq_cross: np.ndarray
    position_sq_cross: np.ndarray
    hist: np.ndarray
    n_flagged_runs: np.ndarray

    @staticmethod
    def empty(n_steps: int) -> StudyMoments:
        S, T = len(SCORE_NAMES), n_steps
        z = np.zeros
        return StudyMoments(
            np.zeros((), np.int64),
            z((S, T)),
            z((S, T)),
            z((T, T)),
            z((T, T)),
            np.zeros((len(HIST_NAMES), _HIST_SIZE), np.int64),
            np.zeros((), np.int64),
        )


def _chan_merge(a: StudyMoments, b: StudyMoments) -> StudyMoments:
    """Merge two accumulators (Chan, Golub & LeVeque's pairwise update), in float64."""
    na, nb = int(a.n), int(b.n)
    if nb == 0:
        return a
    if na == 0:
        return b
    n = na + nb
    d = b.mean - a.mean
    f = na * nb / n
    ds, dp = d[SCORE_NAMES.index("sq_error")], d[SCORE_NAMES.index("position_sq_error")]
    return StudyMoments(
        n=np.asarray(n, np.int64),
        mean=a.mean + d * (nb / n),
        m2=a.m2 + b.m2 + d * d * f,
        sq_cross=a.sq_cross + b.sq_cross + np.outer(ds, ds) * f,
        position_sq_cross=a.position_sq_cross + b.position_sq_cross + np.outer(dp, dp) * f,
        hist=a.hist + b.hist,
        n_flagged_runs=np.asarray(int(a.n_flagged_runs) + int(b.n_flagged_runs), np.int64),
    )


class BlockSums(NamedTuple):
    """A study's accumulators as the complete nodes of one fixed binary tree over its blocks of runs.

    Block ``k`` holds runs ``[k b, (k + 1) b)`` of the whole study (``b = block_size``, the last block
    clipped at ``n_runs``); each is summed by one device in one chunk. Node ``(level, index)`` holds
    blocks ``[index 2^level, (index + 1) 2^level)`` and is the :func:`_chan_merge` of its two children
    (its left child alone where the right one lies past the last block). Every node's value depends on
    its blocks only, never on the order they arrived in, so any split of a study at block boundaries,
    merged, and any resume give the whole study's root bit for bit.

    Attributes:
        block_size: runs per block (``chunk_size / devices``).
        n_blocks: blocks of the whole study, ``ceil(n_runs / block_size)``.
        nodes: ``((level, index, StudyMoments), ...)`` the complete nodes, ordered by first block;
            at most ``2 log2(n_blocks)`` of them (one, the root, for a whole study).
    """

    block_size: int
    n_blocks: int
    nodes: tuple[tuple[int, int, StudyMoments], ...]


def _tree_top(n_blocks: int) -> int:
    """The root's level: the smallest ``L`` with ``2**L >= n_blocks``."""
    return max(0, (n_blocks - 1).bit_length())


def _insert_node(
    nodes: dict[tuple[int, int], StudyMoments], level: int, index: int, m: StudyMoments, n_blocks: int
) -> None:
    """Add node ``(level, index)`` to ``nodes`` and combine upwards while its sibling is there (or empty)."""
    top = _tree_top(n_blocks)
    while level < top:
        sibling = (level, index ^ 1)
        if index % 2 == 0 and (index + 1) << level >= n_blocks:
            pass  # the right sibling lies past the last block: the parent is this node
        elif sibling in nodes:
            other = nodes.pop(sibling)
            m = _chan_merge(other, m) if index % 2 else _chan_merge(m, other)
        else:
            break
        level, index = level + 1, index // 2
    if (level, index) in nodes:
        raise ValueError(f"blocks {index << level}..: summed twice (overlapping runs)")
    nodes[(level, index)] = m


def _block_sums(block_size: int, n_blocks: int, nodes: dict[tuple[int, int], StudyMoments]) -> BlockSums:
    order = sorted(nodes, key=lambda li: li[1] << li[0])
    return BlockSums(block_size, n_blocks, tuple((lv, ix, nodes[(lv, ix)]) for lv, ix in order))


def _fold(sums: BlockSums, n_steps: int) -> StudyMoments:
    """The accumulators of all of ``sums``' runs: the root, or its nodes combined left to right."""
    m = StudyMoments.empty(n_steps)
    for _, _, node in sums.nodes:
        m = _chan_merge(m, node)
    return m


def _hist_index(v, xp):
    """Bin of each value: 0 underflow (incl. 0 and negatives), 1..bins, bins+1 overflow, bins+2 NaN."""
    with np.errstate(divide="ignore", invalid="ignore"):
        pos = (xp.log10(xp.maximum(v, 0)) - HIST_LOG10_LOW) * HIST_BINS_PER_DECADE
        pos = xp.clip(xp.where(xp.isnan(pos), -1.0, pos), -1.0, float(_N_BINS))  # -inf -> underflow
        idx = xp.floor(pos).astype(xp.int32) + 1
    return xp.where(xp.isnan(v), _N_BINS + 2, idx)


class _ShiftedSums(NamedTuple):
    """Sums of one block of runs about a shift (the block's first run), as the device computes them.

    No division, so no program's rounding of one (XLA may multiply by a reciprocal instead) enters
    the block's sums: only additions and products of the runs' own scores. :func:`_centre` turns them
    into :class:`StudyMoments` on the host, in float64.
    """

    n: Any  # () real runs
    shift: Any  # (S, T) the first run's scores
    s1: Any  # (S, T) Σ_i (x_i - shift)
    s2: Any  # (S, T) Σ_i (x_i - shift)²
    sq_gram: Any  # (T, T) Σ_i (e_i - shift)(e_i - shift)^T of the squared error
    position_sq_gram: Any  # (T, T) the same for the position squared error
    hist: Any
    n_flagged_runs: Any


def _shifted_sums(scores: RunScores, mask, xp) -> _ShiftedSums:
    """:class:`_ShiftedSums` of one batch of per-run scores ``(B, T)``; ``mask (B,)`` marks real runs.

    ``xp`` is :mod:`jax.numpy` inside the compiled chunk or :mod:`numpy` on the host.
    """
    dtype = scores.sq_error.dtype
    m = mask[:, None]
    cols = [
        scores.sq_error,
        scores.position_sq_error,
        scores.nees,
        scores.n_components,
        scores.ise,
        scores.cost,
        scores.flags,
    ]
    x = xp.stack([cast(Array, c).astype(dtype) for c in cols])  # (S, B, T)
    shift = xp.where(mask[0], x[:, 0], 0)
    dev = xp.where(m[None], x - shift[:, None], 0)
    hists = []
    for v in (scores.nees, xp.sqrt(scores.position_sq_error.astype(dtype))):
        idx = _hist_index(v, xp)
        w = xp.broadcast_to(m, idx.shape).astype(xp.int32)
        if xp is np:
            h = np.zeros(_HIST_SIZE, np.int64)
            np.add.at(h, idx.ravel(), w.ravel())
        else:
            h = xp.zeros(_HIST_SIZE, xp.int32).at[idx.ravel()].add(w.ravel())
        hists.append(h)
    flagged = (xp.any(scores.flags, axis=1) & mask).astype(xp.int32).sum()
    if xp is np:
        gram = lambda a: a.T @ a  # noqa: E731
    else:
        gram = lambda a: jnp.matmul(a.T, a, precision=jax.lax.Precision.HIGHEST)  # noqa: E731
    i_sq, i_psq = SCORE_NAMES.index("sq_error"), SCORE_NAMES.index("position_sq_error")
    return _ShiftedSums(
        xp.sum(mask.astype(xp.int32)),
        shift,
        dev.sum(1),
        (dev * dev).sum(1),
        gram(dev[i_sq]),
        gram(dev[i_psq]),
        xp.stack(hists),
        flagged,
    )


def _centre(b: _ShiftedSums) -> StudyMoments:
    """The :class:`StudyMoments` of host :class:`_ShiftedSums` (float64; elementwise, so every process
    computes the same bits)."""
    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    n = int(b.n)
    s1 = f64(b.s1)
    c = s1 / max(n, 1)  # the mean's offset from the shift
    i_sq, i_psq = SCORE_NAMES.index("sq_error"), SCORE_NAMES.index("position_sq_error")
    return StudyMoments(
        np.asarray(n, np.int64),
        f64(b.shift) + c,
        f64(b.s2) - s1 * c,
        f64(b.sq_gram) - np.outer(s1[i_sq], c[i_sq]),
        f64(b.position_sq_gram) - np.outer(s1[i_psq], c[i_psq]),
        np.asarray(b.hist, np.int64),
        np.asarray(b.n_flagged_runs, np.int64),
    )


def _hist_median(counts: np.ndarray) -> float:
    """Median of the values binned in ``counts`` (see the module docstring for the accuracy).

    As :func:`numpy.median`, the mean of the order statistics of ranks ``floor((n-1)/2)`` and
    ``ceil((n-1)/2)``; each is placed inside its bin by its rank among the bin's values (log-linear), so
    each is within one bin ratio ``10**(1/1000)`` of the true order statistic.
    """
    counts = np.asarray(counts, np.int64)
    total = int(counts.sum())
    if total == 0 or counts[-1] > 0:
        return float("nan")
    cum = np.cumsum(counts[:-1])

    def order_stat(r: int) -> float:
        j = int(np.searchsorted(cum, r, side="right"))
        if j == 0:
            return 0.0
        if j >= _N_BINS + 1:
            return 10.0**HIST_LOG10_HIGH
        below = cum[j] - counts[j]
        frac = (r - below + 0.5) / counts[j]
        return float(10.0 ** (HIST_LOG10_LOW + (j - 1 + frac) / HIST_BINS_PER_DECADE))

    lo, hi = (total - 1) // 2, total // 2
    return 0.5 * (order_stat(lo) + order_stat(hi))


def _armse_and_stderr(mean_sq: np.ndarray, cross: np.ndarray, n: int) -> tuple[np.ndarray, float, float]:
    """RMSE per step, ARMSE and the ARMSE's Monte Carlo standard error from the accumulators.

    Delta method: ``ARMSE = mean_t sqrt(mean_i e_it)`` is linearised around the per-step means, so
    ``ARMSE ≈ const + mean_i Σ_t a_t e_it`` with ``a_t = 1 / (2 T rmse_t)``; the variance of that
    per-run sum over runs is ``a^T C a`` with ``C = cross / (n - 1)``, the runs' covariance of
    ``e_i``, and the standard error is ``sqrt(a^T C a / n)`` (``nan`` for one run).
    """
    T = mean_sq.shape[0]
    rmse = np.sqrt(mean_sq)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(rmse > 0, 1.0 / (2.0 * T * rmse), 0.0)
    armse = float(rmse.mean()) if T else float("nan")
    if n < 2:
        return rmse, armse, float("nan")
    var = float(a @ cross @ a) / (n - 1)
    return rmse, armse, float(np.sqrt(max(var, 0.0) / n))
