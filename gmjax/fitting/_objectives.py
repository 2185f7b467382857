"""What :func:`gmjax.fitting.fit` minimises: the objectives and their traceable value at unconstrained values.

:func:`~gmjax.fitting.nll` (the negative log-likelihood per step of measurement sequences, single- or
multi-target) and :func:`~gmjax.fitting.study` (a Monte Carlo study loss on a scenario) make an
:class:`~gmjax.fitting.Objective`; this module turns one, with the data and a
:class:`~gmjax.fitting.ParamView`, into the differentiable function ``(u, key) -> ()``
(:func:`~gmjax.fitting.loss_fn`) that the optimiser steps on.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from gmjax._types import Array, PRNGKey
from gmjax.filters.base import Filter, StepInputs, run
from gmjax.fitting._params import ParamView
from gmjax.models.base import Scenario

# ----------------------------------------------------------------------------- objectives


class Objective(NamedTuple):
    """What :func:`fit` minimises: ``kind`` ``"nll"`` (measurements) or ``"study"`` (a scenario)."""

    kind: str
    loss: Callable | None = None
    n_runs: int = 16
    resample: bool = False


def nll() -> Objective:
    """The negative log-likelihood per step, ``-(1 / (B T)) Σ_b Σ_t StepInfo.loglik`` (predict-only steps
    contribute 0), of the filter on the given measurement sequences."""
    return Objective("nll")


def study(loss: Callable | None = None, n_runs: int = 16, *, resample: bool = False) -> Objective:
    """A Monte Carlo study loss (:func:`gmjax.montecarlo.study_loss`): ``loss`` (default ARMSE of the
    position) of ``n_runs`` runs of the scenario; the same runs every step unless ``resample``."""
    if isinstance(n_runs, bool) or not isinstance(n_runs, int) or n_runs < 1:
        raise ValueError(f"n_runs: must be a positive int, got {n_runs!r}")
    return Objective("study", loss, n_runs, resample)


def _is_multitarget_scenario(data: Any) -> bool:
    from gmjax.multitarget.scenarios import MultiTargetScenario

    return isinstance(data, MultiTargetScenario)


def _is_multitarget(filter: Filter) -> bool:
    """A GM-PHD, GM-CPHD or GM-LMB filter: its steps measure padded sets ``(M, m)``."""
    from gmjax.multitarget.cphd import CPHDParams
    from gmjax.multitarget.lmb import LMBParams
    from gmjax.multitarget.phd import PHDParams

    return isinstance(filter.params, (PHDParams, CPHDParams, LMBParams))


def _measurement_data(data: Any, filter: Filter) -> tuple[Array, Any]:
    zs, inputs = data if isinstance(data, tuple) and len(data) == 2 else (data, None)
    zs = jnp.asarray(zs)
    sets = int(_is_multitarget(filter))  # a GM-PHD step measures a padded set (M, m)
    if zs.ndim - sets not in (2, 3) or not jnp.issubdtype(zs.dtype, jnp.floating):
        want = "padded sets (T, M, m) or a batch (B, T, M, m)" if sets else "(T, m) or a batch (B, T, m)"
        raise ValueError(
            f"data: expected float measurements {want}, or (zs, inputs); got {zs.dtype} {zs.shape}"
        )
    return zs, inputs


def _nll_value(filter: Filter, params: Any, zs: Array, inputs: Any, key: PRNGKey) -> Array:
    sets = _is_multitarget(filter)
    if sets:
        from gmjax.multitarget.phd import run as run_sets
    batched = zs.ndim == 3 + sets
    zb = zs if batched else zs[None]
    keys = jax.random.split(key, zb.shape[0])
    if inputs is None or isinstance(inputs, StepInputs) or jnp.ndim(inputs) == 1:
        in_axis = None  # one set of inputs for every sequence
    else:
        in_axis = 0

    def one(z, inp, k):
        return (run_sets if sets else run)(filter, z, inp, key=k, params=params)[1].loglik.sum()

    ll = jax.vmap(one, (0, in_axis, 0))(zb, inputs, keys)
    return -jnp.sum(ll) / (zb.shape[0] * zb.shape[1])


def _value_fn(
    filter: Filter, objective: Objective, scenario: Scenario | None, names, constraints
) -> Callable:
    """``(u, key, base_params, data) -> ()`` with the data and the fixed params as arguments, so one
    compiled program serves every data set of the same shapes."""
    if objective.kind == "study" and _is_multitarget_scenario(scenario):
        from gmjax.multitarget.study import study_loss as mt_study_loss

        def mt_study_value(u, k, base, data):
            del data
            params = ParamView(names, constraints, base).params_at(u)
            return mt_study_loss(filter, scenario, objective.n_runs, k, objective.loss, params=params)

        return mt_study_value
    if objective.kind == "study":
        from gmjax.montecarlo import armse_loss, study_loss

        loss = armse_loss() if objective.loss is None else objective.loss

        def study_value(u, k, base, data):
            del data
            params = ParamView(names, constraints, base).params_at(u)
            return study_loss(filter, scenario, objective.n_runs, k, loss, params=params)

        return study_value

    def nll_value(u, k, base, data):
        zs, inputs = data
        return _nll_value(filter, ParamView(names, constraints, base).params_at(u), zs, inputs, k)

    return nll_value


def _data_args(data: Any, objective: Objective, filter: Filter) -> tuple:
    return () if objective.kind == "study" else _measurement_data(data, filter)


def loss_fn(
    filter: Filter, data: Any, objective: Objective, view: ParamView
) -> Callable[[Any, PRNGKey], Array]:
    """``(u, key) -> ()``: the objective :func:`fit` minimises, at unconstrained values ``u`` (a dict name ->
    array, as :meth:`ParamView.unconstrained` gives); traceable and differentiable."""
    scenario = data if objective.kind == "study" else None
    value = _value_fn(filter, objective, scenario, view.names, view.constraints)
    args = _data_args(data, objective, filter)
    return lambda u, k: value(u, k, view.params, args)
