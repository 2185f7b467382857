"""Batched Monte Carlo studies: simulate, filter and score ``N`` runs in one compiled kernel.

Each run ``i`` uses its own key ``jax.random.split(key, n_runs)[i]`` (split again into a simulation
key and a filter key), so the numbers do not depend on the chunk size or on the number of devices:
on one device they are bit-identical for any chunk size (tested); sharded over several devices,
each device compiles its own per-device batch shape and XLA may reassociate a sum, so they agree to
rounding (tested to 1e-12 relative; 3e-14 observed).
Runs are ``vmap``-ped in chunks that bound memory; each chunk's run axis is sharded over the given
devices with :mod:`jax.sharding` (docs/design.md §5). A progress line over chunks goes to stderr.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import metrics
from gmjax._types import Array, PRNGKey
from gmjax.filters.base import Filter, StepInputs, run
from gmjax.models.base import Scenario, simulate

__all__ = ["RunScores", "MonteCarloResult", "monte_carlo", "score_run"]


class RunScores(NamedTuple):
    """Per-run, per-step scores (leading axes ``(N, T)`` once batched).

    Attributes:
        sq_error: squared error of the full state.
        position_sq_error: squared error of the position components (the full state if the
            scenario names none).
        nees: normalised estimation error squared (seed 001 eq 43).
        n_components: live mixture components after reduction (1 for single-Gaussian filters).
        ise: ISE of the step's reduction (0 where the filter does not report one).
        cost: the reducer's own cost (e.g. PCM's EISE; 0 where none).
        flags: any overflow / covariance repair / degenerate update reported by the filter that step.
        estimates: ``(N, T, d)`` point estimates (kept when ``keep_trajectories``).
        truths: ``(N, T, d)`` true states.
    """

    sq_error: Array
    position_sq_error: Array
    nees: Array
    n_components: Array
    ise: Array
    cost: Array
    flags: Array
    estimates: Array | None
    truths: Array | None


class MonteCarloResult(NamedTuple):
    """Aggregated Monte Carlo study (NumPy arrays, ready to print and plot).

    Attributes:
        rmse: ``(T,)`` RMSE over runs per step (seed 000 eq 44 / seed 001 eq 42).
        position_rmse: ``(T,)`` the same for the position components.
        armse: ``()`` time average of ``rmse`` (ARMSE); ``armse_stderr`` its Monte Carlo standard
            error (delta method over runs).
        position_armse: ``()`` time average of ``position_rmse``; ``position_armse_stderr`` its
            standard error.
        nees: ``(T,)`` average NEES per step; ``anees``: ``()`` over runs and steps;
            ``median_nees``: ``()`` median over runs and steps (robust to the rare step where a
            particle cloud collapses and one NEES explodes).
        cep: ``()`` median position error over all runs and steps (seed 004 eq 24).
        mean_cost: ``()`` time/run average of the reducer's own cost (``ReductionInfo.cost``): the
            AEISE for PCM / GMRCM, a summed KL bound for Runnalls, 0 for pruning; ``mean_ise`` the
            time/run average of the ISE of each reduction.
        n_components: ``(T,)`` mean live components per step.
        flag_rate: ``()`` fraction of steps with an overflow or a repaired covariance.
        scores: the per-run :class:`RunScores`.
        n_runs, compile_s, run_s: bookkeeping (seconds of compilation and of execution).
    """

    rmse: np.ndarray
    position_rmse: np.ndarray
    armse: float
    armse_stderr: float
    position_armse: float
    position_armse_stderr: float
    nees: np.ndarray
    anees: float
    cep: float
    mean_cost: float
    mean_ise: float
    n_components: np.ndarray
    flag_rate: float
    scores: RunScores
    n_runs: int
    compile_s: float
    run_s: float
    median_nees: float = float("nan")


class FilteredRun(NamedTuple):
    """One simulated and filtered run: ``truths``/``estimates`` ``(T, d)``, ``covs`` ``(T, d, d)``,
    the filter's per-step ``infos``, the position dimensions and the per-step failure ``flags``
    (overflow, repaired covariance or degenerate update)."""

    truths: Array
    estimates: Array
    covs: Array
    infos: Any
    position_dims: list[int]
    flags: Array


def filter_run(filter: Filter, scenario: Scenario, key: PRNGKey, params: Any = None) -> FilteredRun:
    """Simulate one run of ``scenario`` and filter it (traceable); shared by the scorers.

    ``params`` overrides ``filter.params`` (differentiate or vmap a study over them).
    """
    k_sim, k_filt = jax.random.split(key)
    xs, zs, ts = simulate(scenario, k_sim)
    truths = xs[1:]
    _, infos = run(filter, zs, StepInputs(t=ts), key=k_filt, params=params)
    pos = list(scenario.position_dims) if scenario.position_dims else list(range(truths.shape[1]))
    return FilteredRun(truths, infos.mean, infos.cov, infos, pos, infos.flags.any())


def score_run(filter: Filter, scenario: Scenario, key: PRNGKey, *, keep_trajectories: bool = False) -> RunScores:
    """Simulate one run of ``scenario``, filter it and score every step (traceable)."""
    r = filter_run(filter, scenario, key)
    truths, est, pos = r.truths, r.estimates, r.position_dims
    T, dtype = truths.shape[0], truths.dtype
    reduction = r.infos.reduction
    ise = r.infos.extra.get("ise")
    return RunScores(
        sq_error=metrics.squared_error(est, truths),
        position_sq_error=metrics.squared_error(est[:, pos], truths[:, pos]),
        nees=metrics.nees(est, r.covs, truths),
        n_components=jnp.asarray(r.infos.n_components, jnp.int32),
        ise=jnp.zeros(T, dtype) if ise is None else jnp.asarray(ise, dtype),
        cost=jnp.zeros(T, dtype) if reduction is None else jnp.asarray(reduction.cost, dtype),
        flags=r.flags,
        estimates=est if keep_trajectories else None,
        truths=truths if keep_trajectories else None,
    )


def _progress(done: int, total: int, started: float, enabled: bool) -> None:
    if not enabled:
        return
    elapsed = time.perf_counter() - started
    rate = done / elapsed if elapsed > 0 else float("inf")
    width = 30
    filled = int(width * done / total)
    end = "\n" if done == total else ""
    sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {done}/{total} runs  {rate:8.1f} runs/s{end}")
    sys.stderr.flush()


def monte_carlo(
    filter: Filter,
    scenario: Scenario,
    n_runs: int,
    key: PRNGKey,
    chunk_size: int | None = None,
    devices: Sequence[jax.Device] | None = None,
    *,
    keep_trajectories: bool = False,
    progress: bool = True,
) -> MonteCarloResult:
    """Run ``n_runs`` independent simulations of ``scenario`` through ``filter`` and score them.

    Args:
        filter: any :class:`~gmjax.filters.Filter` (GSF, local filter, PF, IMM, ...).
        scenario: the :class:`~gmjax.models.Scenario` (true simulator + the model the filter uses).
        n_runs: ``N >= 1``.
        key: PRNG key; run ``i`` uses ``jax.random.split(key, n_runs)[i]``.
        chunk_size: runs per compiled batch (default: all runs, at most 1024); bounds memory.
        devices: devices to shard each chunk's run axis over (default: all local devices).
        keep_trajectories: also return ``(N, T, d)`` estimates and truths.
        progress: print a progress bar over chunks to stderr.

    Returns:
        A :class:`MonteCarloResult`; the same numbers for any ``chunk_size`` and device count.
    """
    if isinstance(n_runs, bool) or not isinstance(n_runs, int) or n_runs < 1:
        raise ValueError(f"n_runs: must be a positive int, got {n_runs!r}")
    if chunk_size is not None and (not isinstance(chunk_size, int) or chunk_size < 1):
        raise ValueError(f"chunk_size: must be a positive int or None, got {chunk_size!r}")
    devices = list(jax.local_devices() if devices is None else devices)
    if not devices:
        raise ValueError("devices: empty device list")
    n_dev = len(devices)
    chunk = min(n_runs, 1024) if chunk_size is None else min(chunk_size, n_runs)
    chunk = n_dev * math.ceil(chunk / n_dev)  # every device gets the same share
    n_chunks = math.ceil(n_runs / chunk)
    keys = jax.random.split(key, n_runs)
    pad = n_chunks * chunk - n_runs
    if pad:
        keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], pad, axis=0)])

    batched = jax.vmap(lambda k: score_run(filter, scenario, k, keep_trajectories=keep_trajectories))
    if n_dev > 1:
        mesh = jax.sharding.Mesh(np.asarray(devices), ("runs",))
        sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("runs"))
        compiled_fn = jax.jit(batched, in_shardings=sharding)
        place = lambda k: jax.device_put(k, sharding)  # noqa: E731
    else:
        compiled_fn = jax.jit(batched)
        place = lambda k: jax.device_put(k, devices[0])  # noqa: E731

    t0 = time.perf_counter()
    compiled = compiled_fn.lower(place(keys[:chunk])).compile()
    compile_s = time.perf_counter() - t0

    parts = []
    t0 = time.perf_counter()
    _progress(0, n_runs, t0, progress)
    for c in range(n_chunks):
        out = compiled(place(keys[c * chunk : (c + 1) * chunk]))
        parts.append(jax.tree_util.tree_map(np.asarray, out))
        _progress(min((c + 1) * chunk, n_runs), n_runs, t0, progress)
    run_s = time.perf_counter() - t0
    scores = jax.tree_util.tree_map(lambda *a: np.concatenate(a)[:n_runs], *parts)
    return summarize(scores, n_runs=n_runs, compile_s=compile_s, run_s=run_s)


def summarize(scores: RunScores, *, n_runs: int, compile_s: float = 0.0, run_s: float = 0.0) -> MonteCarloResult:
    """Aggregate per-run scores ``(N, T)`` into a :class:`MonteCarloResult`."""
    sq = np.asarray(scores.sq_error, np.float64)
    psq = np.asarray(scores.position_sq_error, np.float64)
    rmse, armse_se = _rmse_and_armse_stderr(sq)
    prmse, parmse_se = _rmse_and_armse_stderr(psq)
    return MonteCarloResult(
        rmse=rmse,
        position_rmse=prmse,
        armse=float(rmse.mean()),
        armse_stderr=armse_se,
        position_armse=float(prmse.mean()),
        position_armse_stderr=parmse_se,
        nees=np.asarray(scores.nees).mean(0),
        anees=float(np.mean(scores.nees)),
        cep=float(np.median(np.sqrt(psq))),
        mean_cost=float(np.mean(scores.cost)),
        mean_ise=float(np.mean(scores.ise)),
        n_components=np.asarray(scores.n_components).mean(0),
        flag_rate=float(np.mean(scores.flags)),
        scores=scores,
        n_runs=n_runs,
        compile_s=compile_s,
        run_s=run_s,
        median_nees=float(np.median(scores.nees)),
    )


def _rmse_and_armse_stderr(sq: np.ndarray) -> tuple[np.ndarray, float]:
    """RMSE per step ``(T,)`` of squared errors ``(N, T)`` and the standard error of its time average.

    Delta method: ``ARMSE = mean_t sqrt(mean_i e_it)`` is linearised around the per-step means, so
    ``ARMSE ≈ const + mean_i sum_t e_it / (2 T rmse_t)``; the standard error is that per-run sum's
    standard deviation over ``sqrt(N)``.
    """
    n_runs, T = sq.shape
    rmse = np.sqrt(sq.mean(0))
    grad = 1.0 / (2.0 * T * np.where(rmse > 0, rmse, np.inf))
    per_run = (sq * grad[None, :]).sum(1)
    se = float(per_run.std(ddof=1) / np.sqrt(n_runs)) if n_runs > 1 else float("nan")
    return rmse, se
