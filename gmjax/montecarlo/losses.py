"""Differentiable study losses: per-run scores of a batch of runs and the losses tuning takes."""

from __future__ import annotations

from typing import Any, Callable, cast

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._types import Array, PRNGKey
from gmjax.filters.base import Filter
from gmjax.models.base import Scenario
from gmjax.montecarlo.runs import RunScores, run_key, score_run

__all__ = [
    "study_scores",
    "study_loss",
    "armse_loss",
    "anees_loss",
    "aeise_loss",
    "count_loss",
    "weighted_loss",
]

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
