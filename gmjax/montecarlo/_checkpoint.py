"""Checkpoints of a running study: the configuration that identifies it, written after every chunk,
read back (or refused, naming what differs) on resume."""

from __future__ import annotations

import hashlib
import json
import os
from typing import Any, NamedTuple, Sequence

import jax
import numpy as np

from gmjax._types import PRNGKey
from gmjax.filters.base import Filter
from gmjax.models.base import Scenario
from gmjax.montecarlo._files import _digest, _pack, _read_npz, _unpack, _write_npz
from gmjax.montecarlo.accumulate import BlockSums, _fold
from gmjax.montecarlo.runs import RunScores


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
