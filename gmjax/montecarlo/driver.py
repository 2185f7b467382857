"""The streaming driver :func:`monte_carlo`: chunks sharded over devices and processes, cached compiled
programs, checkpoints, progress."""

from __future__ import annotations

import math
import os
import time
from typing import Any, Sequence, cast

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._jitcache import CachedProgram, IdentityCache
from gmjax._progress import Progress
from gmjax._types import PRNGKey
from gmjax.filters.base import Filter
from gmjax.models.base import Scenario, simulate
from gmjax.montecarlo._checkpoint import _read_checkpoint, _study_config, _write_checkpoint
from gmjax.montecarlo._files import _remove_stale_tmp
from gmjax.montecarlo.accumulate import (
    StudyMoments,
    _block_sums,
    _centre,
    _fold,
    _insert_node,
    _shifted_sums,
    _ShiftedSums,
)
from gmjax.montecarlo.result import MonteCarloResult, _finalize
from gmjax.montecarlo.runs import RunScores, _filter_simulated, _simulate_run, run_key, score_filtered

__all__ = ["monte_carlo", "default_chunk_size"]

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
