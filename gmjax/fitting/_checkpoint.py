"""A fit's step-by-step history and its resumable checkpoint files.

:func:`gmjax.fitting.fit` accumulates its history in a ``_FitLog`` and, with ``checkpoint=path``, writes
the unconstrained values, the optimiser state and that history atomically with a checksum, keyed by a
JSON description of the fit (leaves, constraints, objective, data, start, key, optimiser state's
structure, gmjax version); reading a checkpoint back refuses one of another fit, naming what differs.
"""

from __future__ import annotations

import json
import os
from typing import Any, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._types import Array
from gmjax._version import __version__
from gmjax.fitting._objectives import Objective
from gmjax.fitting._params import ParamView
from gmjax.montecarlo._files import _digest, _read_npz, _write_npz


class _FitLog:
    """The history a fit accumulates, one entry per step (kept in checkpoints)."""

    def __init__(self, names: Sequence[str]):
        self.losses: list[float] = []
        self.gmaxs: list[float] = []
        self.oks: list[bool] = []
        self.values: dict[str, list[np.ndarray]] = {n: [] for n in names}

    @property
    def n_steps(self) -> int:
        return len(self.losses)

    def append(self, loss: float, gmax: float, ok: bool, natural: Mapping[str, Array]) -> None:
        self.losses.append(loss)
        self.gmaxs.append(gmax)
        self.oks.append(ok)
        for n, v in self.values.items():
            v.append(np.asarray(natural[n]))


# ----------------------------------------------------------------------------- checkpoints


def _fit_config(view: ParamView, objective: Objective, data: Any, data_args: tuple, key, opt_state) -> dict:
    """What a fit's checkpoint must agree on to be resumed (JSON-able)."""
    if objective.kind == "study":
        data_id = {
            "scenario": type(data).__name__,
            "name": data.name,
            "n_steps": int(data.n_steps),
            "model": _digest(data.model.params),
        }
    else:
        data_id = {"measurements": _digest(data_args)}
    leaves, treedef = jax.tree_util.tree_flatten(opt_state)
    return {
        "gmjax_version": __version__,
        "fit": list(view.names),
        "constraints": {n: list(c) if isinstance(c, tuple) else c for n, c in view.constraints.items()},
        "objective": {
            "kind": objective.kind,
            "n_runs": objective.n_runs,
            "resample": objective.resample,
            "loss": repr(objective.loss)
            if isinstance(objective.loss, tuple)
            else type(objective.loss).__name__,
        },
        "data": data_id,
        "start": _digest(view.params),
        "key": np.asarray(jax.random.key_data(key)).ravel().tolist(),
        "optimizer_state": {
            "structure": str(treedef),
            "leaves": [[list(np.shape(x)), str(np.asarray(x).dtype)] for x in leaves],
        },
    }


_FIT_RESTART = "delete it or pass resume=False to start the fit again"


def _write_fit_checkpoint(path, config: dict, u: Mapping[str, Array], state: Any, log: _FitLog) -> None:
    arrays: dict[str, np.ndarray] = {
        "fit_config": np.asarray(json.dumps(config, sort_keys=True)),
        "loss": np.asarray(log.losses, np.float64),
        "grad_max": np.asarray(log.gmaxs, np.float64),
        "ok": np.asarray(log.oks, bool),
    }
    for i, n in enumerate(config["fit"]):
        arrays[f"u/{i}"] = np.asarray(u[n])
        arrays[f"values/{i}"] = np.stack(log.values[n])
    for i, leaf in enumerate(jax.tree_util.tree_leaves(state)):
        arrays[f"state/{i}"] = np.asarray(leaf)
    _write_npz(path, arrays)


def _read_fit_checkpoint(path, config: dict, u0: dict, state0: Any, names: Sequence[str]) -> tuple:
    name = os.fspath(path)
    try:
        f = _read_npz(path, "checkpoint")
    except ValueError as e:
        raise ValueError(f"{e}; {_FIT_RESTART}") from None
    if "fit_config" not in f or "checksum" not in f:
        raise ValueError(f"checkpoint: {name!r} is not a gmjax fit checkpoint; {_FIT_RESTART}")
    old = json.loads(str(f["fit_config"]))
    if old != config:
        diff = sorted(k for k in set(old) | set(config) if old.get(k) != config.get(k))
        raise ValueError(
            f"checkpoint: {name!r} was written by another fit (differs in: {', '.join(diff)}); "
            f"{_FIT_RESTART}, or pass another path"
        )
    u = {n: jnp.asarray(f[f"u/{i}"], u0[n].dtype) for i, n in enumerate(names)}
    leaves, treedef = jax.tree_util.tree_flatten(state0)
    state = jax.tree_util.tree_unflatten(
        treedef, [jnp.asarray(f[f"state/{i}"], jnp.asarray(x).dtype) for i, x in enumerate(leaves)]
    )
    log = _FitLog(names)
    log.losses = [float(x) for x in f["loss"]]
    log.gmaxs = [float(x) for x in f["grad_max"]]
    log.oks = [bool(x) for x in f["ok"]]
    log.values = {n: list(f[f"values/{i}"]) for i, n in enumerate(names)}
    return u, state, log
