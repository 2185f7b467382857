"""A differentiable multi-target Monte Carlo study loss: the mean relaxed GOSPA of a GM-PHD filter.

:func:`study_loss` simulates ``n_runs`` runs of a :class:`MultiTargetScenario` (run ``i`` from
``jax.random.fold_in(key, i)``, split into a simulation and a filter key), runs the filter with the
given ``params`` on each, and averages a per-scan loss over runs and scans. The default,
:func:`gospa_loss`, is the relaxed GOSPA^p of :func:`~gmjax.multitarget.phd.soft_estimates` against the
live true positions (:func:`~gmjax.multitarget.metrics.soft_gospa`), so ``jax.grad`` reaches every
leaf of :class:`~gmjax.multitarget.PHDParams` (clutter rate, birth weights and covariances, a relaxed
reducer's thresholds); :func:`gmjax.fit` minimises it with ``fitting.study(gospa_loss(c=...))``.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from gmjax._types import Array, PRNGKey
from gmjax.filters.base import Filter
from gmjax.multitarget.metrics import soft_gospa
from gmjax.multitarget.phd import PHDState, run, soft_estimates
from gmjax.multitarget.scenarios import MultiTargetSample, MultiTargetScenario, simulate

__all__ = ["GospaLoss", "gospa_loss", "study_loss"]


class GospaLoss(NamedTuple):
    """Per-scan relaxed GOSPA^p (``alpha = 2``) of the posterior intensity's soft estimates.

    Attributes:
        c, p: GOSPA's cut-off and order.
        threshold, temperature: :func:`~gmjax.multitarget.phd.soft_estimates`' extraction threshold
            and sigmoid temperature (0: the hard rule, whose gradient in the weights is 0).
        max_copies: estimates per component.
    """

    c: float
    p: float = 2.0
    threshold: float = 0.5
    temperature: float = 0.05
    max_copies: int = 2

    def __call__(self, states: PHDState, sample: MultiTargetSample, position_dims: tuple[int, ...]) -> Array:
        """``()``: the mean over scans of GOSPA^p for one run (``states`` with a leading ``T`` axis)."""
        dims = jnp.asarray(position_dims)

        def scan_loss(intensity, truth, alive):
            cand, e = soft_estimates(intensity, self.threshold, self.temperature, max_copies=self.max_copies)
            g = soft_gospa(cand[:, dims], truth[:, dims], e, alive, c=self.c, p=self.p)
            return g.distance**self.p

        return jnp.mean(jax.vmap(scan_loss)(states.intensity, sample.states, sample.alive))


def gospa_loss(
    c: float, p: float = 2.0, *, threshold: float = 0.5, temperature: float = 0.05, max_copies: int = 2
) -> GospaLoss:
    """The relaxed GOSPA^p loss of :class:`GospaLoss` (``c`` has the units of the positions)."""
    for name, v in (("c", c), ("p", p)):
        if not (isinstance(v, (int, float)) and v > 0):
            raise ValueError(f"{name}: must be a positive number, got {v!r}")
    if not (isinstance(temperature, (int, float)) and temperature >= 0):
        raise ValueError(f"temperature: must be >= 0, got {temperature!r}")
    if isinstance(max_copies, bool) or not isinstance(max_copies, int) or max_copies < 1:
        raise ValueError(f"max_copies: must be a positive int, got {max_copies!r}")
    return GospaLoss(float(c), float(p), float(threshold), float(temperature), max_copies)


def study_loss(
    filter: Filter,
    scenario: MultiTargetScenario,
    n_runs: int,
    key: PRNGKey,
    loss: Callable[[PHDState, MultiTargetSample, tuple[int, ...]], Array] | None = None,
    *,
    params: Any = None,
) -> Array:
    """Mean ``loss`` over ``n_runs`` simulated runs of ``scenario`` filtered with ``params``.

    Args:
        filter: a GM-PHD :class:`~gmjax.filters.Filter` (:func:`~gmjax.multitarget.gm_phd`).
        scenario: the :class:`MultiTargetScenario` to simulate (the truth does not depend on ``params``).
        n_runs: runs (static).
        key: run ``i`` splits ``fold_in(key, i)`` into its simulation key and its filter key.
        loss: ``(states, sample, position_dims) -> ()`` per run (default: ``gospa_loss(c=100)``).
        params: the filter's params (default ``filter.params``); differentiable.

    Returns:
        ``()`` the mean loss.
    """
    if not isinstance(scenario, MultiTargetScenario):
        raise ValueError(f"scenario: expected a MultiTargetScenario, got {type(scenario).__name__}")
    if isinstance(n_runs, bool) or not isinstance(n_runs, int) or n_runs < 1:
        raise ValueError(f"n_runs: must be a positive int, got {n_runs!r}")
    per_run = gospa_loss(100.0) if loss is None else loss
    params = filter.params if params is None else params
    dims = tuple(scenario.position_dims)

    def one(i):
        k_sim, k_filter = jax.random.split(jax.random.fold_in(key, i))
        sample = simulate(scenario, k_sim)
        states, _ = run(filter, sample.zs, key=k_filter, params=params)
        return per_run(states, sample, dims)

    return jnp.mean(jax.vmap(one)(jnp.arange(n_runs)))
