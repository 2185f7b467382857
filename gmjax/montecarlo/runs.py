"""One run of a study: its key, simulation, filtering and per-step scores."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from gmjax import metrics
from gmjax._types import Array, PRNGKey
from gmjax.filters.base import Filter, StepInputs, run
from gmjax.models.base import Scenario, simulate

__all__ = ["RunScores", "FilteredRun", "run_key", "filter_run", "score_run", "score_filtered"]

SCORE_NAMES = ("sq_error", "position_sq_error", "nees", "n_components", "ise", "cost", "flags")


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
