"""Monte Carlo studies at any scale: streaming, resumable, split across runs and hosts, differentiable.

**Runs and keys.** Run ``i`` of a study with key ``key`` uses ``run_key(key, i) =
jax.random.fold_in(key, i)``, which under JAX's default (partitionable) threefry equals
``jax.random.split(key, n_runs)[i]`` (tested), split again into a simulation and a filter key. A run's
key depends on its index only, so a study can run any range of its runs (``runs=range(a, b)``), on any
number of processes, and the parts :func:`merge` into the whole.

**Streaming.** :func:`monte_carlo` runs the study in chunks of ``chunk_size`` runs. Two programs are
compiled for the chunk shape (the last chunk is padded and masked), so every chunk runs the same code:
the simulation of the chunk's runs, kept per scenario object, chunk size and devices so that every
filter studied on the same scenario object reuses it (as :func:`gmjax.studies.run_study` does), and the
filter with its scoring, kept per filter, scenario and params object. ``compile_s`` counts a program
only in the study that compiled it. Each device of a chunk sums its own **block** of ``chunk_size /
devices`` runs: per step, the sum and sum of squares of every score (squared error, position squared
error, NEES, component count, ISE, reducer cost, flags) about the block's first run, the ``(T, T)``
cross-products of the squared errors (for the ARMSE standard error, see :func:`_armse_and_stderr`),
log-spaced histograms of the NEES and of the position error (for the median NEES and the CEP) and the
number of runs with a flag. The host centres each block in float64 and combines the blocks (Chan et
al.'s pairwise update) in one fixed binary tree over the study's block indices (:class:`BlockSums`),
keeping only its complete nodes, so memory is ``O(chunk T + T² log2(N / block))`` whatever ``n_runs``
is; each node's ``(T, T)`` cross-moments cost 8 T² bytes twice (0.23 MB at T = 120, 16 MB at T = 1000).
Full per-run scores are kept for the first ``keep_runs`` runs.

**Medians.** ``median_nees`` and ``cep`` come from fixed histograms with 1000 bins per decade over
``[1e-10, 1e10]``: each middle order statistic is found in its bin and placed inside it by its rank
(log-linear), so the median's relative error is below ``10**(1/1000) - 1 = 0.23 %`` (values under
1e-10 read as 0, values above 1e10 as 1e10; a NaN anywhere gives NaN, as :func:`numpy.median` does).

**Determinism.** A study's numbers depend on its runs and its block size only. Block ``k`` always holds
runs ``[k b, (k + 1) b)``; each block is summed by the same per-device program (its scores materialised
before they are summed, and no division on the device, so no fused multiply-add or reciprocal of one
program's choosing enters the sums), and the tree combines the blocks in an order fixed by their
indices, never by their arrival. So with the same block size, a study is bit-identical (every field
of the result, every accumulator) whatever the split of its runs at block boundaries into parts
merged by :func:`merge` (in any order), an interruption and resume, and the number of devices and
processes: a chunk of 8 runs on 4 devices gives the bits of a chunk of 2 on one (tested, with two
processes under ``jax.distributed`` too). :func:`monte_carlo` refuses ranges off the block grid
(their partial blocks would be summed in other groups). Across block sizes, numbers agree to
rounding only: XLA compiles each batch shape on its own and may vectorise it differently. Measured on
seed 000's jump system (30 steps, 12-24 runs, CPU): per-run scores were identical for chunk sizes 5,
8, 12 and 24 with NL-, R- and PCM-GSFs and a PF, but a chunk of 1 (compiled unbatched) changed
PCM-GSF's per-run squared errors by up to 8e-5 relative in float32 and 2e-13 in float64; and the sums
are grouped otherwise (ARMSE: 3e-8 relative in float32, 1e-16 in float64). The test checks chunk
sizes to 1e-12 relative in float64.

**Resume.** ``checkpoint=path`` writes the block sums after every chunk (``.npz``, no pickle, with a
sha256 checksum of its arrays; a temporary file and :func:`os.replace`, temporary files of a killed
write removed on start and finish) with a hash of the configuration (filter params, scenario settings,
key, run range, block size, dtype, gmjax and JAX versions). Calling again with the same arguments
resumes after the last finished chunk and returns the bit-identical result, on any number of devices
with the same block size. A checkpoint that is truncated, empty, corrupt (checksum), written by
another gmjax or by a different configuration is refused with a ``ValueError`` naming the file, the
cause (what differs) and the remedy (delete it, or ``resume=False``).

**Many devices and hosts.** Each chunk's run axis is sharded over a 1-D mesh of ``devices`` (default
``jax.devices()``: every device of every process), one block per device. Under
``jax.distributed.initialize`` every process gathers every block's sums, so every process combines the
same blocks in the same tree and returns the same result. Launch one process per host with the same
script::

    # SLURM: srun --nodes=4 --ntasks-per-node=1 python study.py
    import jax
    jax.distributed.initialize()   # reads SLURM_* (or pass coordinator_address, num_processes, process_id)
    result = gmjax.monte_carlo(filt, scenario, 10**7, jax.random.key(0), progress=jax.process_index() == 0)
    if jax.process_index() == 0:
        result.save("study.npz")

On CPU hosts, the cross-process collectives are gloo (``jax_cpu_collectives_implementation``, JAX's
default).

**Differentiable studies.** :func:`study_scores` (per-run scores ``(N, T)``, ``vmap`` of
:func:`score_run`) and :func:`study_loss` are traceable: ``jax.grad`` of a study loss w.r.t. a
``params`` pytree that replaces ``filter.params`` (a relaxed reducer's threshold, a noise covariance)
goes through simulation, filtering and scoring. :mod:`gmjax.tune` is an optax loop over
:func:`study_loss`.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import time
import zipfile
import zlib
from typing import Any, Callable, NamedTuple, Sequence, cast

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import metrics
from gmjax._jitcache import CachedProgram, IdentityCache
from gmjax._progress import Progress
from gmjax._types import Array, PRNGKey
from gmjax.filters.base import Filter, StepInputs, run
from gmjax.models.base import Scenario, simulate

__all__ = [
    "RunScores",
    "StudyMoments",
    "MonteCarloResult",
    "BlockSums",
    "FilteredRun",
    "monte_carlo",
    "default_chunk_size",
    "merge",
    "summarize",
    "load_result",
    "run_key",
    "filter_run",
    "score_run",
    "score_filtered",
    "study_scores",
    "study_loss",
    "armse_loss",
    "anees_loss",
    "aeise_loss",
    "count_loss",
    "weighted_loss",
]

SCORE_NAMES = ("sq_error", "position_sq_error", "nees", "n_components", "ise", "cost", "flags")
HIST_NAMES = ("nees", "position_error")
HIST_LOG10_LOW, HIST_LOG10_HIGH, HIST_BINS_PER_DECADE = -10.0, 10.0, 1000
_N_BINS = int((HIST_LOG10_HIGH - HIST_LOG10_LOW) * HIST_BINS_PER_DECADE)
_HIST_SIZE = _N_BINS + 3  # [underflow (incl. 0), bins..., overflow, NaN]


# ----------------------------------------------------------------------------- one run


class RunScores(NamedTuple):
    """Per-run, per-step scores (leading axes ``(N, T)`` once batched).

    Attributes:
        sq_error: squared error of the full state.
        position_sq_error: squared error of the position components (the full state if the
            scenario names none).
        nees: normalised estimation error squared (seed 001 eq 43).
        cost: the reducer's own cost (e.g. PCM's EISE; 0 where none).
        flags: any flag of the filter's :class:`~gmjax.filters.StepFlags` raised that step (every
            field is reduced, so new flags are counted too).
        n_components: live mixture components after reduction (1 for single-Gaussian filters).
        ise: ISE of the step's reduction (0 where the filter does not report one).
        n_expected: expected live components (``info.reduction.aux["n_expected"]`` of a relaxed
            reducer, else the live count): the differentiable component count.
        estimates: ``(N, T, d)`` point estimates (kept with ``keep_trajectories``).
        truths: ``(N, T, d)`` true states (kept with ``keep_trajectories``).
    """

    sq_error: Array
    position_sq_error: Array
    nees: Array
    cost: Array
    flags: Array
    n_components: Array | None = None
    ise: Array | None = None
    n_expected: Array | None = None
    estimates: Array | None = None
    truths: Array | None = None


class FilteredRun(NamedTuple):
    """One simulated and filtered run: ``truths``/``estimates`` ``(T, d)``, ``covs`` ``(T, d, d)``,
    the filter's per-step ``infos``, the position dimensions and the per-step ``flags`` (any field
    of ``infos.flags``)."""

    truths: Array
    estimates: Array
    covs: Array
    infos: Any
    position_dims: list[int]
    flags: Array


def run_key(key: PRNGKey, index: Any) -> PRNGKey:
    """The key of run ``index`` of a study (``= jax.random.split(key, n)[index]`` for any ``n > index``
    under JAX's default partitionable threefry)."""
    return jax.random.fold_in(key, index)


def _any_flag(flags: Any) -> Array:
    leaves = jax.tree_util.tree_leaves(flags)
    out = jnp.zeros(jnp.shape(leaves[0]), bool) if leaves else jnp.zeros((), bool)
    for leaf in leaves:
        out = out | jnp.asarray(leaf, bool)
    return out


class _SimulatedRun(NamedTuple):
    """One simulated run, ready to filter: ``truths (T, d)``, ``zs (T, m)``, the ``StepInputs`` and the
    filter's key."""

    truths: Array
    zs: Array
    inputs: StepInputs
    filter_key: PRNGKey


def _simulate_run(scenario: Scenario, key: PRNGKey) -> _SimulatedRun:
    k_sim, k_filt = jax.random.split(key)
    xs, zs, steps = simulate(scenario, k_sim)  # steps: the times, or the scenario's StepInputs
    inputs = steps if isinstance(steps, StepInputs) else StepInputs(t=steps)
    return _SimulatedRun(xs[1:], zs, inputs, k_filt)


def _filter_simulated(filter: Filter, scenario: Scenario, sim: _SimulatedRun, params: Any) -> FilteredRun:
    _, infos = run(filter, sim.zs, sim.inputs, key=sim.filter_key, params=params)
    truths = sim.truths
    pos = list(scenario.position_dims) if scenario.position_dims else list(range(truths.shape[1]))
    return FilteredRun(truths, infos.mean, infos.cov, infos, pos, _any_flag(infos.flags))


def filter_run(filter: Filter, scenario: Scenario, key: PRNGKey, params: Any = None) -> FilteredRun:
    """Simulate one run of ``scenario`` and filter it (traceable); shared by the scorers.

    ``params`` overrides ``filter.params`` (differentiate or vmap a study over them).
    """
    return _filter_simulated(filter, scenario, _simulate_run(scenario, key), params)


def score_run(
    filter: Filter, scenario: Scenario, key: PRNGKey, *, params: Any = None, keep_trajectories: bool = False
) -> RunScores:
    """Simulate one run of ``scenario``, filter it and score every step (traceable, differentiable)."""
    return score_filtered(filter_run(filter, scenario, key, params), keep_trajectories=keep_trajectories)


def score_filtered(r: FilteredRun, *, keep_trajectories: bool = False) -> RunScores:
    """Score every step of a :class:`FilteredRun` (for scorers that also read ``r.infos``)."""
    truths, est, pos = r.truths, r.estimates, r.position_dims
    T, dtype = truths.shape[0], truths.dtype
    reduction = r.infos.reduction
    ise = r.infos.extra.get("ise")
    n_exp = None if reduction is None else reduction.aux.get("n_expected")
    n_comp = jnp.asarray(r.infos.n_components, jnp.int32)
    return RunScores(
        sq_error=metrics.squared_error(est, truths),
        position_sq_error=metrics.squared_error(est[:, pos], truths[:, pos]),
        nees=metrics.nees(est, r.covs, truths),
        cost=jnp.zeros(T, dtype) if reduction is None else jnp.asarray(reduction.cost, dtype),
        flags=r.flags,
        n_components=n_comp,
        ise=jnp.zeros(T, dtype) if ise is None else jnp.asarray(ise, dtype),
        n_expected=jnp.asarray(n_comp if n_exp is None else n_exp, dtype),
        estimates=est if keep_trajectories else None,
        truths=truths if keep_trajectories else None,
    )


# ----------------------------------------------------------------------------- differentiable studies


def study_scores(
    filter: Filter,
    scenario: Scenario,
    n_runs: int,
    key: PRNGKey,
    params: Any = None,
    *,
    runs: range | None = None,
) -> RunScores:
    """Simulate, filter and score ``n_runs`` runs in one ``vmap`` (traceable and differentiable).

    Run ``i`` uses :func:`run_key` ``(key, i)`` exactly as :func:`monte_carlo` does, so the same key gives
    the same runs in both.

    Args:
        filter: any :class:`~gmjax.filters.Filter`.
        scenario: the :class:`~gmjax.models.Scenario` to simulate.
        n_runs: static number of runs.
        key: PRNG key.
        params: a pytree replacing ``filter.params`` (default: ``filter.params``), e.g. with a traced
            reducer threshold or noise covariance, to ``jax.grad`` / ``jax.vmap`` the study over it.
        runs: the run indices (default ``range(n_runs)``).

    Returns:
        :class:`RunScores` with leading axes ``(len(runs), T)``.
    """
    runs = range(n_runs) if runs is None else runs
    idx = jnp.asarray(np.asarray(runs, np.uint32))
    keys = jax.vmap(run_key, (None, 0))(key, idx)
    return jax.vmap(lambda k: score_run(filter, scenario, k, params=params))(keys)


def study_loss(
    filter: Filter,
    scenario: Scenario,
    n_runs: int,
    key: PRNGKey,
    loss: Callable[[RunScores], Array] | None = None,
    params: Any = None,
) -> Array:
    """A differentiable Monte Carlo score of ``filter`` on ``scenario``: ``loss(study_scores(...))``.

    ``jax.grad(lambda p: study_loss(filt, sc, 16, key, armse_loss(), params=p))(filt.params)`` is the
    gradient of the study's ARMSE w.r.t. every leaf of the filter's params. Hard decisions (a pruning
    threshold, a split trigger) have zero gradient; relax them with the reducer's own
    ``mode="soft"`` and temperature (see :mod:`gmjax.reduction.relax`).

    Args:
        filter, scenario, n_runs, key, params: as in :func:`study_scores`.
        loss: ``RunScores -> ()`` (default :func:`armse_loss` of the position components), e.g.
            :func:`anees_loss`, :func:`count_loss`, :func:`weighted_loss`.

    Returns:
        ``()`` the loss.
    """
    loss = armse_loss() if loss is None else loss
    return loss(study_scores(filter, scenario, n_runs, key, params))


def armse_loss(*, position: bool = True) -> Callable[[RunScores], Array]:
    """ARMSE ``mean_t sqrt(mean_i e²_it)`` (seed 000 eq 44), of the position components by default."""

    def loss(scores: RunScores) -> Array:
        sq = scores.position_sq_error if position else scores.sq_error
        return jnp.mean(jnp.sqrt(jnp.mean(sq, axis=0)))

    return loss


def anees_loss(target: float) -> Callable[[RunScores], Array]:
    """``|ANEES - d|``: consistency (the ANEES of a consistent filter is the state dimension ``d``)."""

    def loss(scores: RunScores) -> Array:
        return jnp.abs(jnp.mean(scores.nees) - target)

    return loss


def aeise_loss() -> Callable[[RunScores], Array]:
    """AEISE: the reducer's EISE (seed 000 eq 29) averaged over runs and steps."""
    return lambda scores: jnp.mean(scores.cost)


def count_loss() -> Callable[[RunScores], Array]:
    """Expected number of components after reduction, averaged over runs and steps (a cost)."""
    return lambda scores: jnp.mean(cast(Array, scores.n_expected))


def weighted_loss(*terms: tuple[float, Callable[[RunScores], Array]]) -> Callable[[RunScores], Array]:
    """``Σ_i c_i loss_i``; e.g. ``weighted_loss((1.0, armse_loss()), (0.01, count_loss()))``."""
    if not terms:
        raise ValueError("terms: need at least one (weight, loss) pair")
    for t in terms:
        if not (isinstance(t, tuple) and len(t) == 2 and callable(t[1])):
            raise ValueError(f"terms: expected (weight, loss) pairs, got {t!r}")

    def loss(scores: RunScores) -> Array:
        return cast(Array, sum(float(c) * f(scores) for c, f in terms))

    return loss


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


# ----------------------------------------------------------------------------- results


class MonteCarloResult(NamedTuple):
    """Aggregated Monte Carlo study (NumPy arrays, ready to print, plot, save and merge).

    Attributes:
        rmse: ``(T,)`` RMSE over runs per step (seed 000 eq 44 / seed 001 eq 42).
        position_rmse: ``(T,)`` the same for the position components.
        armse: ``()`` time average of ``rmse`` (ARMSE); ``armse_stderr`` its Monte Carlo standard
            error (delta method over runs; ``nan`` for one run).
        position_armse, position_armse_stderr: the same for ``position_rmse``.
        nees: ``(T,)`` average NEES per step; ``anees``: ``()`` over runs and steps;
            ``median_nees``: ``()`` median over runs and steps (histogram, < 0.23 % relative error),
            robust to the rare step where a particle cloud collapses and one NEES explodes.
        cep: ``()`` median position error over all runs and steps (seed 004 eq 24; histogram).
        mean_cost: ``()`` time/run average of the reducer's own cost (``ReductionInfo.cost``): the
            AEISE for PCM / GMRCM, a summed KL bound for Runnalls, 0 for pruning; ``mean_ise`` the
            time/run average of the ISE of each reduction (``nan`` when the filter does not report
            ``extra["ise"]``, e.g. a GSF built without ``track_ise``).
        n_components: ``(T,)`` mean live components per step.
        flag_rate: ``()`` fraction of steps with any flag; ``n_runs_flagged``: runs with any flag.
        n_runs: runs in the result; ``runs``: ``(start, stop)`` of the run indices.
        moments: the :class:`StudyMoments` behind every number (what :func:`merge` combines).
        scores: :class:`RunScores` ``(k, T)`` of the first ``k = keep_runs`` runs, or ``None``.
        config: the study's configuration (dtype, key, runs, chunk size, versions, ...; JSON-ready).
        compile_s, run_s: seconds of compilation (the filter's program, plus the simulation's when
            this study compiled it: see "Streaming" above) and of execution; ``resumed_runs``: runs
            taken from a checkpoint.
        sums: the :class:`BlockSums` that ``moments`` folds (what :func:`merge` combines, bit for
            bit); ``None`` for a result of :func:`summarize`.
    """

    rmse: np.ndarray
    position_rmse: np.ndarray
    armse: float
    armse_stderr: float
    position_armse: float
    position_armse_stderr: float
    nees: np.ndarray
    anees: float
    median_nees: float
    cep: float
    mean_cost: float
    mean_ise: float
    n_components: np.ndarray
    flag_rate: float
    n_runs_flagged: int
    n_runs: int
    runs: tuple[int, int]
    moments: StudyMoments
    scores: RunScores | None = None
    config: dict | None = None
    compile_s: float = 0.0
    run_s: float = 0.0
    resumed_runs: int = 0
    sums: BlockSums | None = None

    def to_json(self) -> dict:
        """JSON-ready summary (no per-run data; NaN / inf as ``None``)."""
        out = {}
        for name in (
            "armse",
            "armse_stderr",
            "position_armse",
            "position_armse_stderr",
            "anees",
            "median_nees",
            "cep",
            "mean_cost",
            "mean_ise",
            "flag_rate",
            "n_runs_flagged",
            "n_runs",
            "compile_s",
            "run_s",
            "resumed_runs",
        ):
            out[name] = getattr(self, name)
        for name in ("rmse", "position_rmse", "nees", "n_components"):
            out[name] = np.asarray(getattr(self, name)).tolist()
        out["runs"] = list(self.runs)
        out["config"] = self.config
        return json_safe(out)

    def save(self, path: str | os.PathLike) -> None:
        """Write the result to ``path`` (``.npz``: accumulators, block sums, kept runs, a JSON header
        and a sha256 checksum of all of it; no pickle)."""
        arrays = _pack(self.moments, self.sums, self.scores)
        meta = {
            "runs": list(self.runs),
            "config": self.config,
            "compile_s": self.compile_s,
            "run_s": self.run_s,
            "resumed_runs": self.resumed_runs,
            "ise_tracked": not np.isnan(self.mean_ise),
        }
        arrays["meta"] = np.asarray(json.dumps(json_safe(meta)))
        _write_npz(path, arrays)

    @staticmethod
    def load(path: str | os.PathLike) -> MonteCarloResult:
        """Read a result written by :meth:`save`."""
        return load_result(path)


def load_result(path: str | os.PathLike) -> MonteCarloResult:
    """Read a :class:`MonteCarloResult` written by :meth:`MonteCarloResult.save` (no pickle).

    Raises:
        ValueError: naming ``path`` and the cause, when the file is missing, truncated, corrupt
            (checksum) or not a saved result.
    """
    f = _read_npz(path, "result", required=("meta",))
    meta = json.loads(str(f["meta"]))
    moments, sums, scores = _unpack(f)
    return _finalize(
        moments,
        runs=tuple(meta["runs"]),
        scores=scores,
        config=meta["config"],
        compile_s=meta["compile_s"] or 0.0,
        run_s=meta["run_s"] or 0.0,
        resumed_runs=meta["resumed_runs"],
        ise_tracked=meta.get("ise_tracked", True),
        sums=sums,
    )


# ----------------------------------------------------------------------------- files


def _pack(moments: StudyMoments, sums: BlockSums | None, scores: RunScores | None) -> dict[str, np.ndarray]:
    """The arrays of a result or checkpoint file (``moments.*``, ``sums.*`` stacked by node, ``scores.*``)."""
    arrays = {f"moments.{k}": np.asarray(v) for k, v in moments._asdict().items()}
    if sums is not None:
        arrays["sums.block_size"] = np.asarray(sums.block_size, np.int64)
        arrays["sums.n_blocks"] = np.asarray(sums.n_blocks, np.int64)
        arrays["sums.level"] = np.asarray([lv for lv, _, _ in sums.nodes], np.int64)
        arrays["sums.index"] = np.asarray([ix for _, ix, _ in sums.nodes], np.int64)
        for k in StudyMoments._fields:
            arrays[f"sums.{k}"] = np.stack([np.asarray(getattr(m, k)) for _, _, m in sums.nodes])
    if scores is not None:
        arrays.update({f"scores.{k}": np.asarray(v) for k, v in scores._asdict().items() if v is not None})
    return arrays


def _unpack(f: dict[str, np.ndarray]) -> tuple[StudyMoments, BlockSums | None, RunScores | None]:
    moments = StudyMoments(**{k: f[f"moments.{k}"] for k in StudyMoments._fields})
    sums = None
    if "sums.level" in f:
        nodes = tuple(
            (int(lv), int(ix), StudyMoments(**{k: f[f"sums.{k}"][j] for k in StudyMoments._fields}))
            for j, (lv, ix) in enumerate(zip(f["sums.level"], f["sums.index"]))
        )
        sums = BlockSums(int(f["sums.block_size"]), int(f["sums.n_blocks"]), nodes)
    kept: dict[str, Any] = {k[len("scores.") :]: f[k] for k in f if k.startswith("scores.")}
    return moments, sums, (RunScores(**kept) if kept else None)


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    """sha256 of every array's name, dtype, shape and bytes (in name order; ``checksum`` itself excluded)."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        if name == "checksum":
            continue
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _tmp_path(path: str) -> str:
    return f"{path}.tmp-{os.getpid()}.npz"


def _remove_stale_tmp(path: str | os.PathLike) -> None:
    """Remove the temporary files that writes to ``path`` left behind (a write killed half-way)."""
    import glob

    for tmp in glob.glob(glob.escape(os.fspath(path)) + ".tmp-*.npz"):
        with contextlib.suppress(OSError):
            os.remove(tmp)


def _write_npz(path: str | os.PathLike, arrays: dict) -> None:
    """Write ``arrays`` and their checksum atomically: a temporary file, fsync, :func:`os.replace`."""
    path = os.fspath(path)
    arrays = dict(arrays, checksum=np.asarray(_checksum(arrays)))
    tmp = _tmp_path(path)
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):
            os.remove(tmp)


def _read_npz(path: str | os.PathLike, what: str, required: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """Every array of a file written by :func:`_write_npz`, its checksum verified (files written
    before gmjax kept checksums have none: the caller decides whether to accept them).

    Raises:
        ValueError: naming the file and the cause (missing, not an ``.npz``, truncated, checksum
            mismatch, ``required`` arrays missing).
    """
    name = os.fspath(path)
    try:
        with np.load(name, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except FileNotFoundError:
        raise ValueError(f"{what}: {name!r} does not exist") from None
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as e:
        cause = "empty" if os.path.exists(name) and os.path.getsize(name) == 0 else "truncated or corrupt"
        raise ValueError(
            f"{what}: {name!r} is {cause} and cannot be read ({type(e).__name__}: {e})"
        ) from None
    missing = [k for k in required if k not in arrays]
    if missing:
        raise ValueError(f"{what}: {name!r} is not a gmjax Monte Carlo {what} file (no {', '.join(missing)})")
    if "checksum" in arrays and str(arrays["checksum"]) != _checksum(arrays):
        raise ValueError(
            f"{what}: {name!r} is corrupt: its contents do not match the checksum it was written with"
        )
    return arrays


def json_safe(obj: Any) -> Any:
    """``obj`` with NaN / inf floats replaced by ``None`` and NumPy scalars by Python ones (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def _finalize(
    m: StudyMoments,
    *,
    runs: tuple[int, int],
    scores: RunScores | None = None,
    config: dict | None = None,
    compile_s: float = 0.0,
    run_s: float = 0.0,
    resumed_runs: int = 0,
    ise_tracked: bool = True,
    sums: BlockSums | None = None,
) -> MonteCarloResult:
    n = int(m.n)
    i = SCORE_NAMES.index
    rmse, armse, se = _armse_and_stderr(m.mean[i("sq_error")], m.sq_cross, n)
    prmse, parmse, pse = _armse_and_stderr(m.mean[i("position_sq_error")], m.position_sq_cross, n)

    def avg(name):
        row = m.mean[i(name)]
        return float(row.mean()) if row.size else float("nan")

    return MonteCarloResult(
        rmse=rmse,
        position_rmse=prmse,
        armse=armse,
        armse_stderr=se,
        position_armse=parmse,
        position_armse_stderr=pse,
        nees=m.mean[i("nees")].copy(),
        anees=avg("nees"),
        median_nees=_hist_median(m.hist[0]),
        cep=_hist_median(m.hist[1]),
        mean_cost=avg("cost"),
        mean_ise=avg("ise") if ise_tracked else float("nan"),
        n_components=m.mean[i("n_components")].copy(),
        flag_rate=avg("flags"),
        n_runs_flagged=int(m.n_flagged_runs),
        n_runs=n,
        runs=(int(runs[0]), int(runs[1])),
        moments=m,
        scores=scores,
        config=config,
        compile_s=float(compile_s),
        run_s=float(run_s),
        resumed_runs=int(resumed_runs),
        sums=sums,
    )


def summarize(
    scores: RunScores, *, n_runs: int | None = None, compile_s: float = 0.0, run_s: float = 0.0
) -> MonteCarloResult:
    """Aggregate per-run scores ``(N, T)`` (e.g. of :func:`study_scores`) into a :class:`MonteCarloResult`."""
    sq = np.asarray(scores.sq_error, np.float64)
    N, T = sq.shape
    if n_runs is not None and n_runs != N:
        raise ValueError(f"n_runs: {n_runs} but the scores hold {N} runs")

    def col(x: Any, default: float = 0.0) -> Any:  # host (N, T) float64 columns
        return np.full((N, T), default) if x is None else np.asarray(x, np.float64)

    s = RunScores(
        col(sq),
        col(scores.position_sq_error),
        col(scores.nees),
        col(scores.cost),
        cast(Any, np.asarray(scores.flags, bool)),
        col(scores.n_components, 1.0),
        col(scores.ise),
    )
    moments = _centre(_shifted_sums(s, np.ones(N, bool), np))
    return _finalize(
        moments,
        runs=(0, N),
        scores=scores,
        compile_s=compile_s,
        run_s=run_s,
        ise_tracked=scores.ise is not None,
    )


_SAME_STUDY = ("key", "filter", "scenario", "dtype", "n_runs")  # what makes results parts of one study
_SAME_SUMS = ("block_size", "gmjax_version", "jax_version")  # and what makes their sums combine exactly


def merge(results: Sequence[MonteCarloResult], *, exact: bool = True) -> MonteCarloResult:
    """Combine results of adjoining run ranges of one study into the result of their union.

    With ``exact=True`` (the default) the parts' :class:`BlockSums` are combined in the study's one
    fixed tree, so the merged numbers are bit-identical to one study over all the runs, however the
    runs were split (at block boundaries; :func:`monte_carlo` refuses ranges off them) and in whatever
    order the parts come. ``exact=False`` also takes results without block sums (of :func:`summarize`,
    or saved by an older gmjax) or with different block sizes or versions, and combines their
    accumulators in run order: equal to the whole study to rounding only. Kept runs are concatenated
    in run order (each part's first ``keep_runs``).

    Raises:
        ValueError: no results; overlapping ranges; a gap (a merged result never has a hole: the
            message names the missing runs); parts of different studies (``key``, ``filter``,
            ``scenario``, ``dtype`` or ``n_runs`` differ) or, with ``exact``, whose sums do not
            combine bit for bit (``block_size``, ``gmjax_version`` or ``jax_version`` differ, or no
            block sums): each message names the field.
    """
    results = sorted(results, key=lambda r: r.runs[0])
    if not results:
        raise ValueError("results: nothing to merge")
    for a, b in zip(results, results[1:]):
        if b.runs[0] < a.runs[1]:
            raise ValueError(f"results: run ranges {a.runs} and {b.runs} overlap")
        if b.runs[0] > a.runs[1]:
            raise ValueError(
                f"results: runs {a.runs[1]}..{b.runs[0] - 1} are missing between the parts {a.runs} and "
                f"{b.runs}; run runs=range({a.runs[1]}, {b.runs[0]}) of the study and merge it too"
            )
    fields = _SAME_STUDY + (_SAME_SUMS if exact else ())
    ref = results[0].config or {}
    for r in results[1:]:
        cfg = r.config or {}
        for field in fields:
            if ref.get(field) != cfg.get(field):
                what = "different studies" if field in _SAME_STUDY else "sums that do not combine exactly"
                hint = "" if field in _SAME_STUDY else "; merge(..., exact=False) combines them to rounding"
                raise ValueError(
                    f"results: {what} ({field} differs: {ref.get(field)!r} in {results[0].runs} vs "
                    f"{cfg.get(field)!r} in {r.runs}){hint}"
                )
    n_steps = results[0].moments.mean.shape[1]
    sums = None
    if exact:
        for r in results:
            if r.sums is None:
                raise ValueError(
                    f"results: the part with runs {r.runs} has no block sums (a result of summarize, or saved "
                    "by an older gmjax), so it cannot be merged bit for bit; merge(..., exact=False) "
                    "combines its accumulators to rounding"
                )
        block, n_blocks = results[0].sums.block_size, results[0].sums.n_blocks  # type: ignore[union-attr]
        nodes: dict[tuple[int, int], StudyMoments] = {}
        for r in results:
            for level, index, node in r.sums.nodes:  # type: ignore[union-attr]
                _insert_node(nodes, level, index, node, n_blocks)
        sums = _block_sums(block, n_blocks, nodes)
        m = _fold(sums, n_steps)
    else:
        m = StudyMoments.empty(n_steps)
        for r in results:
            m = _chan_merge(m, r.moments)
    kept = [r.scores for r in results if r.scores is not None]
    scores = None
    if kept:
        scores = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *kept)
    runs = (results[0].runs[0], results[-1].runs[1])
    config = dict(ref, runs=list(runs), merged_from=[list(r.runs) for r in results], exact=exact)
    return _finalize(
        m,
        runs=runs,
        scores=scores,
        config=config,
        compile_s=sum(r.compile_s for r in results),
        run_s=sum(r.run_s for r in results),
        ise_tracked=not any(np.isnan(r.mean_ise) for r in results),
        sums=sums,
    )


# ----------------------------------------------------------------------------- configuration & checkpoints


def _digest(tree: Any) -> str:
    """sha256 of a pytree's structure and leaf values (shape, dtype, bytes)."""
    h = hashlib.sha256()
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    h.update(str(treedef).encode())
    for leaf in leaves:
        a = np.asarray(leaf)
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _study_config(
    filter: Filter,
    scenario: Scenario,
    params: Any,
    key: PRNGKey,
    n_runs: int,
    runs: range,
    chunk: int,
    devices: Sequence[Any],
    keep_runs: int,
    keep_traj: bool,
    dtype: Any,
) -> dict:
    from gmjax._version import __version__

    key_data = np.asarray(jax.random.key_data(key)).ravel().tolist()
    return {
        "gmjax_version": __version__,
        "jax_version": jax.__version__,
        "dtype": str(np.dtype(dtype)),
        "key": {"impl": str(jax.random.key_impl(key)), "data": key_data},
        "n_runs": n_runs,
        "runs": [runs.start, runs.stop],
        "chunk_size": chunk,
        "block_size": chunk // len(devices),
        "devices": {"count": len(devices), "platform": devices[0].platform, "processes": jax.process_count()},
        "keep_runs": keep_runs,
        "keep_trajectories": keep_traj,
        "scenario": {
            "name": scenario.name,
            "n_steps": scenario.n_steps,
            "position_dims": list(scenario.position_dims or []),
            "model_params": _digest(scenario.model.params),
            "description": hashlib.sha256(scenario.description.encode()).hexdigest()[:16],
        },
        "filter": {"params": _digest(filter.params if params is None else params)},
    }


_NOT_IN_CHECKPOINT_IDENTITY = ("chunk_size", "devices")  # the numbers depend on block_size, not on these


def _checkpoint_identity(config: dict) -> dict:
    """What a checkpoint must agree on to be resumed: everything but how the blocks were scheduled."""
    return {k: v for k, v in config.items() if k not in _NOT_IN_CHECKPOINT_IDENTITY}


def _config_hash(config: dict) -> str:
    return hashlib.sha256(json.dumps(_checkpoint_identity(config), sort_keys=True).encode()).hexdigest()


class _Checkpoint(NamedTuple):
    next_run: int
    sums: BlockSums
    kept: RunScores | None


def _write_checkpoint(path, config: dict, next_run: int, sums: BlockSums, kept: list) -> None:
    cat = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *kept) if kept else None
    arrays = _pack(_fold(sums, config["scenario"]["n_steps"]), sums, cat)
    arrays["config_hash"] = np.asarray(_config_hash(config))
    arrays["config"] = np.asarray(json.dumps(config, sort_keys=True))
    arrays["next_run"] = np.asarray(next_run, np.int64)
    _write_npz(path, arrays)


_RESTART = "delete it or pass resume=False to start the study again"


def _read_checkpoint(path, config: dict) -> _Checkpoint:
    name = os.fspath(path)
    try:
        f = _read_npz(path, "checkpoint", required=("config_hash", "config", "next_run"))
    except ValueError as e:
        raise ValueError(f"{e}; {_RESTART}") from None
    old = json.loads(str(f["config"]))
    if old.get("gmjax_version") != config["gmjax_version"] or "checksum" not in f:
        by = "an older gmjax" if "checksum" not in f else f"gmjax {old.get('gmjax_version')}"
        raise ValueError(
            f"checkpoint: {name!r} was written by {by}, this is gmjax {config['gmjax_version']} "
            f"(a checkpoint resumes bit for bit only with the gmjax that wrote it); {_RESTART}"
        )
    if str(f["config_hash"]) != _config_hash(config):
        now, then = _checkpoint_identity(config), _checkpoint_identity(old)
        diff = sorted(k for k in set(now) | set(then) if now.get(k) != then.get(k))
        raise ValueError(
            f"checkpoint: {name!r} was written by another study configuration "
            f"(differs in: {', '.join(diff)}); {_RESTART}, or pass another path"
        )
    _, sums, kept = _unpack(f)
    if sums is None:  # pragma: no cover - every checkpoint with a checksum has block sums
        raise ValueError(f"checkpoint: {name!r} holds no block sums; {_RESTART}")
    return _Checkpoint(int(f["next_run"]), sums, kept)


# ----------------------------------------------------------------------------- the driver


def _validate(filter: Filter, scenario: Scenario, params: Any) -> Any:
    """The study's dtype; refuse a filter whose floating params differ from the scenario's dtype."""
    dtype = np.dtype(scenario.model.prior.means.dtype)
    p = filter.params if params is None else params
    others = {
        np.dtype(leaf.dtype)
        for leaf in jax.tree_util.tree_leaves(p)
        if isinstance(leaf, (np.ndarray, jax.Array)) and jnp.issubdtype(leaf.dtype, jnp.floating)
    }
    others.discard(dtype)
    if others:
        raise ValueError(
            f"filter: its params hold {sorted(map(str, others))} arrays but the scenario "
            f"{scenario.name!r} is {dtype}; build both with the same dtype"
        )
    if dtype == np.float64 and not jax.config.read("jax_enable_x64"):
        raise ValueError("scenario: float64 arrays but jax_enable_x64 is off")
    try:
        xs, zs, _ = jax.eval_shape(lambda k: simulate(scenario, k), jax.random.key(0))
    except TypeError as e:
        lines = [ln for ln in str(e).splitlines() if "has type" in ln] or [str(e).strip()]
        raise ValueError(
            f"scenario: {scenario.name!r} ({dtype}) cannot be simulated: its samplers or "
            f"dynamics return another dtype ({lines[0].strip()})"
        ) from None
    if xs.dtype != dtype or zs.dtype != dtype:
        raise ValueError(
            f"scenario: {scenario.name!r} is {dtype} but simulates {xs.dtype} states and "
            f"{zs.dtype} measurements"
        )
    return dtype


_SIMULATION_PROGRAMS = IdentityCache(maxsize=16)


def _simulation_program(scenario: Scenario, chunk: int, mesh: jax.sharding.Mesh) -> CachedProgram:
    """jit of ``(key, start) -> _SimulatedRun`` batched over runs ``start .. start + chunk - 1``, kept
    per scenario object, chunk size and mesh: the filters of one study share one simulation program."""

    runs_sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("runs"))

    def make() -> CachedProgram:
        def fn(key, start):
            idx = start + jnp.arange(chunk, dtype=jnp.uint32)
            keys = jax.vmap(run_key, (None, 0))(key, jax.lax.with_sharding_constraint(idx, runs_sharding))
            return jax.vmap(lambda k: _simulate_run(scenario, k))(keys)

        return CachedProgram(jax.jit(fn, out_shardings=runs_sharding))

    return _SIMULATION_PROGRAMS.get((scenario,), make, tag=(chunk, mesh))


def _chunk_program(
    filter: Filter,
    scenario: Scenario,
    params: Any,
    chunk: int,
    keep: bool,
    keep_traj: bool,
    mesh: jax.sharding.Mesh,
):
    """jit of ``(_SimulatedRun batch, valid (chunk,) bool) -> (StudyMoments, RunScores | None)`` for
    ``chunk`` runs (the output of :func:`_simulation_program`), and a dict filled when it is traced:
    ``"ise_tracked"``, whether the filter reports ``extra["ise"]``.

    Each device filters and sums its own block of ``chunk / devices`` runs (a ``shard_map``): the
    moments come back stacked, one block per device (leading axis ``devices``), never reduced across
    devices, so a block's sums do not depend on how many devices or processes shared the chunk.
    """
    P = jax.sharding.PartitionSpec
    meta: dict[str, bool] = {}

    def per_device(sims, valid):
        def one(sim):
            r = _filter_simulated(filter, scenario, sim, params)
            meta["ise_tracked"] = "ise" in r.infos.extra
            return score_filtered(r, keep_trajectories=keep_traj)

        # the barrier materialises every run's scores before they are summed: fused into the sums, the
        # scores' last operations round differently from program to program (a fused multiply-add)
        scores = jax.lax.optimization_barrier(jax.vmap(one)(sims))
        sums = jax.tree_util.tree_map(lambda a: a[None], _shifted_sums(scores, valid, jnp))
        return (sums, scores) if keep else sums

    out_specs = (P("runs"), P("runs")) if keep else P("runs")
    sharded = jax.shard_map(
        per_device, mesh=mesh, in_specs=(P("runs"), P("runs")), out_specs=out_specs, check_vma=False
    )

    def fn(sims, valid):
        out = sharded(sims, valid)
        return out if keep else (out, None)

    return CachedProgram(jax.jit(fn)), meta


_CHUNK_PROGRAMS = IdentityCache(maxsize=16)


def _cached_chunk_program(filter, scenario, params, chunk, keep, keep_traj, mesh):
    """:func:`_chunk_program`, kept per filter, scenario and params object, chunk size and mesh, so the
    parts of a study run in one process (or its reruns) compile once."""
    return _CHUNK_PROGRAMS.get(
        (filter, scenario, params),
        lambda: _chunk_program(filter, scenario, params, chunk, keep, keep_traj, mesh),
        tag=(chunk, keep, keep_traj, mesh),
    )


def _host(x) -> np.ndarray:
    """A (replicated or run-sharded) global array as NumPy on this process."""
    if x.is_fully_addressable:
        return np.asarray(x)
    if x.sharding.is_fully_replicated:
        return np.asarray(x.addressable_shards[0].data)
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def default_chunk_size(n_runs: int) -> int:
    """The chunk a study of ``n_runs`` runs gets by default: the largest of 1, 2, 5, 10, 20, 50, ...,
    1000 that is at most ``ceil(n_runs / 10)`` (so the progress bar moves 10 to 25 times, and round
    splits of the study, e.g. halves of 10^6 runs, fall on block boundaries)."""
    target = min(1000, max(1, math.ceil(n_runs / 10)))
    return max(c for c in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000) if c <= target)


def _as_key(key: Any) -> PRNGKey:
    """A typed PRNG key from ``key`` (a typed key, or raw ``uint32`` key data); a clear error otherwise."""
    if isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        if key.shape != ():
            raise ValueError(f"key: expected one PRNG key, got an array of {key.shape} keys")
        return key
    shape = np.shape(key)
    dtype = getattr(key, "dtype", None)
    if dtype is not None and np.dtype(dtype) == np.uint32 and len(shape) == 1:
        try:
            return jax.random.wrap_key_data(jnp.asarray(key, jnp.uint32))
        except (TypeError, ValueError) as e:
            raise ValueError(f"key: {shape} uint32 array is not key data of the default PRNG ({e})") from None
    raise ValueError(
        f"key: expected a PRNG key such as jax.random.key(0), got {type(key).__name__} {key!r:.60}"
    )


def monte_carlo(
    filter: Filter,
    scenario: Scenario,
    n_runs: int,
    key: PRNGKey,
    chunk_size: int | None = None,
    devices: Sequence[jax.Device] | None = None,
    *,
    runs: range | None = None,
    params: Any = None,
    keep_runs: int | None = None,
    keep_trajectories: bool = False,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = True,
    progress: bool | str = True,
) -> MonteCarloResult:
    """Run ``n_runs`` independent simulations of ``scenario`` through ``filter`` and score them.

    Args:
        filter: any :class:`~gmjax.filters.Filter` (GSF, local filter, PF, IMM, ...).
        scenario: the :class:`~gmjax.models.Scenario` (true simulator + the model the filter uses).
        n_runs: ``N >= 1``, the size of the whole study (fixes nothing but the valid run indices).
        key: PRNG key (``jax.random.key(seed)``, or legacy ``uint32`` key data); run ``i`` uses
            :func:`run_key` ``(key, i)`` (``= jax.random.split(key, N)[i]``).
        chunk_size: runs per compiled batch (default :func:`default_chunk_size` ``(n_runs)``: about a
            tenth of the study, at most 1000); rounded up to a multiple of the device count. Each device
            sums a block of ``chunk_size / devices`` runs; the numbers depend on that block size, never on
            the split, the resume or the devices (module docstring, "Determinism"). Memory is
            ``O(chunk_size T + T² log2(N / block))``.
        devices: devices to shard each chunk's run axis over (default ``jax.devices()``: under
            ``jax.distributed`` every process's devices).
        runs: the run indices to do (default ``range(n_runs)``), a ``range`` with step 1 whose start and
            stop lie on the study's block grid (multiples of the block size, or ``stop = n_runs``);
            parts of one study :func:`merge` into the whole bit for bit.
        params: a pytree replacing ``filter.params``.
        keep_runs: keep the per-run :class:`RunScores` of the first ``keep_runs`` runs of ``runs``
            (default 0, or all runs with ``keep_trajectories``).
        keep_trajectories: also keep the kept runs' ``(k, T, d)`` estimates and truths.
        checkpoint: path of an ``.npz`` checkpoint to resume from and update after every chunk (under
            ``jax.distributed``, process 0 writes it: put it where every process can read it). Its
            temporary files (of a write that was killed) are removed on start and finish.
        resume: with ``checkpoint``, continue from an existing checkpoint file (default); ``False``
            starts the study again and overwrites it.
        progress: compilation notice and a progress bar (runs/s, ETA) on stderr; a string labels the
            bar (default label: the scenario's name); ``False``: quiet.

    Returns:
        A :class:`MonteCarloResult`.

    Raises:
        ValueError: bad arguments (naming them), a filter whose dtype differs from the scenario's, a
            range off the block grid, or a checkpoint that is corrupt, of another gmjax or written by a
            different configuration (naming the file and what to do).
    """
    if isinstance(n_runs, bool) or not isinstance(n_runs, (int, np.integer)) or n_runs < 1:
        raise ValueError(f"n_runs: must be a positive int, got {n_runs!r}")
    n_runs = int(n_runs)
    if n_runs >= 2**32:
        raise ValueError(f"n_runs: at most 2**32 - 1 runs, got {n_runs}")
    bad_type = isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer))
    if chunk_size is not None and (bad_type or chunk_size < 1):
        raise ValueError(f"chunk_size: must be a positive int or None, got {chunk_size!r}")
    runs = range(n_runs) if runs is None else runs
    if not isinstance(runs, range) or runs.step != 1 or not 0 <= runs.start < runs.stop <= n_runs:
        raise ValueError(
            f"runs: expected a non-empty range(a, b) with 0 <= a < b <= n_runs = {n_runs}, got {runs!r}"
        )
    if scenario.n_steps < 1:
        raise ValueError(f"scenario: n_steps must be >= 1 to score a study, got {scenario.n_steps}")
    if keep_runs is None:
        keep_runs = len(runs) if keep_trajectories else 0
    if isinstance(keep_runs, bool) or not isinstance(keep_runs, (int, np.integer)) or keep_runs < 0:
        raise ValueError(f"keep_runs: must be a non-negative int, got {keep_runs!r}")
    keep_runs = min(int(keep_runs), len(runs))
    dtype = _validate(filter, scenario, params)
    key = _as_key(key)
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("devices: empty device list")
    n_dev = len(devices)
    chunk = default_chunk_size(n_runs) if chunk_size is None else int(chunk_size)
    chunk = n_dev * math.ceil(chunk / n_dev)  # every device gets the same share
    block = chunk // n_dev
    if runs.start % block or (runs.stop % block and runs.stop != n_runs):
        lo, hi = runs.start - runs.start % block, runs.stop - runs.stop % block
        raise ValueError(
            f"runs: {runs!r} is off the study's block grid (blocks of {block} runs: chunk_size {chunk} on "
            f"{n_dev} device(s)); start and stop must be multiples of {block} (or stop = n_runs = {n_runs}), "
            f"e.g. range({lo}, {hi if hi > lo else lo + block}), so that the parts merge bit for bit"
        )
    config = _study_config(
        filter, scenario, params, key, n_runs, runs, chunk, devices, keep_runs, keep_trajectories, dtype
    )

    n_blocks = math.ceil(n_runs / block)
    nodes: dict[tuple[int, int], StudyMoments] = {}
    kept: list[RunScores] = []
    next_run = runs.start
    writer = checkpoint is not None and jax.process_index() == 0
    if writer:
        _remove_stale_tmp(cast(str, checkpoint))
    if checkpoint is not None and resume and os.path.exists(checkpoint):
        saved = _read_checkpoint(checkpoint, config)
        next_run, nodes = saved.next_run, {(lv, ix): m for lv, ix, m in saved.sums.nodes}
        kept = [] if saved.kept is None else [saved.kept]
    resumed = next_run - runs.start

    label = progress if isinstance(progress, str) else (scenario.name or "study")
    bar = Progress(len(runs), desc=label, unit="runs", enabled=bool(progress), initial=resumed)
    mesh = jax.sharding.Mesh(np.asarray(devices), ("runs",))
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    runs_sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("runs"))
    simulation = _simulation_program(scenario, chunk, mesh)
    program, meta = _cached_chunk_program(
        filter, scenario, params, chunk, keep_runs > 0, keep_trajectories, mesh
    )

    def put(x, sharding=replicated):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda i: x[i])

    def valid_runs(n_valid: int) -> jax.Array:  # (chunk,) bool, sharded as the runs: which are real
        return put(np.arange(chunk) < n_valid, runs_sharding)

    key_arr = jax.random.wrap_key_data(put(jax.random.key_data(key)), impl=jax.random.key_impl(key))
    compile_s = 0.0
    t0 = time.perf_counter()
    sims_shape = jax.eval_shape(simulation.jitted, key_arr, put(np.uint32(0)))
    sims_shape = jax.tree_util.tree_map(
        lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=runs_sharding), sims_shape
    )
    if next_run >= runs.stop:
        program.jitted.trace(sims_shape, valid_runs(0))  # fills meta; nothing to run
        bar.update(0)
    else:
        with bar.compiling(f"{chunk} runs per chunk"):
            simulate_chunk, compile_s = simulation.compile(key_arr, put(np.uint32(0)))
            compiled, filter_compile_s = program.compile(sims_shape, valid_runs(0))
            compile_s += filter_compile_s
        t0 = time.perf_counter()
        while next_run < runs.stop:
            n_valid = min(chunk, runs.stop - next_run)
            sims = simulate_chunk(key_arr, put(np.uint32(next_run)))
            out_m, out_s = compiled(sims, valid_runs(n_valid))
            blocks = jax.tree_util.tree_map(_host, out_m)  # one block per device
            for d in range(n_dev):
                if blocks.n[d] > 0:
                    leaf = _centre(_ShiftedSums(*(a[d] for a in blocks)))
                    _insert_node(nodes, 0, next_run // block + d, leaf, n_blocks)
            n_keep = runs.start + keep_runs - next_run
            if n_keep > 0:
                host_s = jax.tree_util.tree_map(_host, out_s)
                n_take = min(n_keep, n_valid)
                kept.append(jax.tree_util.tree_map(lambda a, n=n_take: a[:n], host_s))
            next_run += n_valid
            if writer:
                _write_checkpoint(checkpoint, config, next_run, _block_sums(block, n_blocks, nodes), kept)
            bar.update(n_valid)
    run_s = time.perf_counter() - t0
    if writer:
        _remove_stale_tmp(cast(str, checkpoint))
    scores = None
    if keep_runs:
        scores = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *kept) if len(kept) > 1 else kept[0]
    sums = _block_sums(block, n_blocks, nodes)
    return _finalize(
        _fold(sums, scenario.n_steps),
        runs=(runs.start, runs.stop),
        scores=scores,
        config=config,
        compile_s=compile_s,
        run_s=run_s,
        resumed_runs=resumed,
        ise_tracked=meta["ise_tracked"],
        sums=sums,
    )
