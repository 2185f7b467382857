"""Tune reduction thresholds (or any filter parameter) by gradient descent on a Monte Carlo loss.

Every reduction threshold of the papers (``ρ`` of the censored pruning, seed 000 eqs 19–22; ``λ`` of
the similarity clustering, eqs 23–28; a weight threshold; the split threshold ``ψ_th`` of seed 001
eq 31) makes a *hard* decision, so a Monte Carlo loss is piecewise constant in it. The reducers
relax their own decisions (a static ``mode`` and a traced temperature, DESIGN §3):
``PruneThreshold(mode="soft", temperature=T)``, ``PruneCensored(mode="soft", temperature=T)``,
``PCM(lam=λ, mode="soft", gate_temperature=T_ρ, temperature=τ)``; the primitives (soft step, gates,
soft memberships) and the soft split trigger of :mod:`gmjax.filters.agsf` are in
:mod:`gmjax.reduction.relax` (:func:`soft_split_gate` is re-exported here).

This module holds the loop: :func:`tune` is an optax loop over :func:`gmjax.montecarlo.study_loss`, the
differentiable Monte Carlo study (simulation, filtering and scoring of a batch of runs), with a loss
(:func:`armse_loss`, :func:`anees_loss`, :func:`aeise_loss`, :func:`count_loss`, :func:`weighted_loss`,
all from :mod:`gmjax.montecarlo` and re-exported here) and updates of unconstrained parameters mapped
into each parameter's valid range (:class:`Bounds`). :func:`study_scores` / :func:`study_loss` also take
a ``params`` pytree that replaces ``filter.params``; :func:`plot_history` plots a run.

:func:`tune` names the tuned thresholds as leaves of ``filter.params`` (``{"reducer.rho": 0.95}``), as
:func:`gmjax.fit` (:mod:`gmjax.fitting`) does, the general form: any leaf (arrays too), maximum
likelihood or a study loss, constraints, convergence and resumable checkpoints. A factory
``params -> Filter`` (version 0.1) is still taken.
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._plotting import plot_curves
from gmjax._progress import Progress
from gmjax._types import Array, PRNGKey
from gmjax.filters.base import Filter
from gmjax.fitting import with_leaves
from gmjax.models import Scenario
from gmjax.montecarlo import (
    RunScores,
    aeise_loss,
    anees_loss,
    armse_loss,
    count_loss,
    study_loss,
    study_scores,
    weighted_loss,
)
from gmjax.reduction.relax import soft_split_gate as soft_split_gate

__all__ = [
    "soft_split_gate",
    "Bounds",
    "TuneScores",
    "TuneHistory",
    "TuneResult",
    "study_scores",
    "study_loss",
    "armse_loss",
    "anees_loss",
    "aeise_loss",
    "count_loss",
    "weighted_loss",
    "tune",
    "plot_history",
]


# ----------------------------------------------------------------------------- differentiable studies
# One implementation: the differentiable study and its losses live in gmjax.montecarlo.

TuneScores = RunScores  # 0.1 name of the per-run scores


# ----------------------------------------------------------------------------- reparameterisation


class Bounds(NamedTuple):
    """Valid range of one parameter: ``(low, high)``, either end ``None`` for unbounded.

    ``(lo, hi)`` maps ``u`` to ``lo + (hi - lo) σ(u)``; ``(lo, None)`` to ``lo + softplus(u)``;
    ``(None, hi)`` to ``hi - softplus(-u)``; ``(None, None)`` is the identity. With ``log=True``
    (``0 < lo < hi``) the interval is covered in log scale, ``exp(log lo + (log hi - log lo) σ(u))``,
    for thresholds that span decades.
    """

    low: float | None = None
    high: float | None = None
    log: bool = False

    def to_constrained(self, u: Array) -> Array:
        lo, hi = self.low, self.high
        if self.log:
            assert lo is not None and hi is not None  # a log bound has both ends (checked on construction)
            a, b = math.log(lo), math.log(hi)
            return jnp.exp(a + (b - a) * jax.nn.sigmoid(u))
        if lo is not None and hi is not None:
            return lo + (hi - lo) * jax.nn.sigmoid(u)
        if lo is not None:
            return lo + jax.nn.softplus(u)
        if hi is not None:
            return hi - jax.nn.softplus(-u)
        return u

    def to_unconstrained(self, x: float) -> float:
        lo, hi = self.low, self.high
        if self.log:
            assert lo is not None and hi is not None
            p = (math.log(x) - math.log(lo)) / (math.log(hi) - math.log(lo))
            return math.log(p) - math.log1p(-p)
        if lo is not None and hi is not None:
            p = (x - lo) / (hi - lo)
            return math.log(p) - math.log1p(-p)
        if lo is not None:
            y = x - lo
            return y + math.log(-math.expm1(-y))
        if hi is not None:
            y = hi - x
            return -(y + math.log(-math.expm1(-y)))
        return x

    def contains(self, x: float) -> bool:
        return (self.low is None or x > self.low) and (self.high is None or x < self.high)


def _as_bounds(b: Any, name: str) -> Bounds:
    if b is None:
        return Bounds()
    if isinstance(b, Bounds):
        out = b
    elif isinstance(b, (tuple, list)) and len(b) == 2:
        out = Bounds(None if b[0] is None else float(b[0]), None if b[1] is None else float(b[1]))
    else:
        raise ValueError(f"bounds[{name!r}]: expected (low, high) or Bounds, got {b!r}")
    if out.low is not None and out.high is not None and not out.low < out.high:
        raise ValueError(f"bounds[{name!r}]: need low < high, got {b!r}")
    if out.log and (out.low is None or out.high is None or not out.low > 0):
        raise ValueError(f"bounds[{name!r}]: log scale needs 0 < low < high, got {b!r}")
    return out


class TuneHistory(NamedTuple):
    """What :func:`tune` did, step by step (NumPy arrays; ``steps`` rows).

    Attributes:
        loss: ``(steps,)`` loss at the parameters of that step (on that step's runs).
        params: name -> ``(steps,)`` the (constrained) parameters evaluated at each step.
        grads: name -> ``(steps,)`` d loss / d parameter (constrained) at each step.
        ok: ``(steps,)`` bool, the loss and gradient were finite (else the update was skipped).
        flag_rate: ``(steps,)`` fraction of filter steps flagged (overflow / repair / degenerate).
        step_s: ``(steps,)`` wall seconds of each step (the first includes compilation).
    """

    loss: np.ndarray
    params: dict[str, np.ndarray]
    grads: dict[str, np.ndarray]
    ok: np.ndarray
    flag_rate: np.ndarray
    step_s: np.ndarray


class TuneResult(NamedTuple):
    """Outcome of :func:`tune`: ``params`` (name -> float, after the last update) and ``history``."""

    params: dict[str, float]
    history: TuneHistory
    compile_s: float


def _leaf_factory(filt: Filter, params0: Mapping[str, float]) -> Callable[[dict[str, Array]], Filter]:
    """``params -> filt`` with the leaves of ``filt.params`` named in ``params0`` set (checked here)."""
    try:
        with_leaves(filt.params, {n: jnp.asarray(float(v)) for n, v in params0.items()})
    except ValueError as e:
        raise ValueError(f"params0: {e} (tune takes scalar leaves)") from None
    return lambda p: filt._replace(params=with_leaves(filt.params, p))


def tune(
    filter_factory: Filter | Callable[[dict[str, Array]], Filter],
    scenario: Scenario,
    params0: Mapping[str, float],
    loss: Callable[[TuneScores], Array],
    optimizer: Any = None,
    n_runs: int = 16,
    steps: int = 20,
    *,
    key: PRNGKey,
    bounds: Mapping[str, Any] | None = None,
    resample: bool = True,
    ad: str = "forward",
    progress: bool = True,
) -> TuneResult:
    """Tune thresholds by gradient descent on a Monte Carlo loss.

    The parameters are leaves of the filter's ``params``, as everywhere else (:func:`study_loss`,
    :func:`gmjax.fit`): ``tune(filt, sc, {"reducer.rho": 0.9}, ...)`` tunes ``filt.params.reducer.rho``
    (names as :func:`gmjax.fitting.leaf_names` lists them; scalar leaves). A factory
    ``params -> Filter`` (version 0.1) is still taken.

    Each step simulates ``n_runs`` runs of ``scenario`` (:func:`study_scores`), filters them with
    the filter at ``params`` and differentiates ``loss(scores)`` with respect to the parameters.
    The optimiser acts on unconstrained values ``u`` with ``params = bounds.to_constrained(u)``, so
    every threshold stays in its valid range. With ``resample`` each step draws fresh runs
    (stochastic gradient; step ``s`` uses ``fold_in(key, s)``), otherwise every step reuses the runs
    of ``key`` itself (common random numbers: a deterministic objective, the same runs as
    ``study_scores(..., key)`` and ``gmjax.monte_carlo(..., key)``). The whole step (simulation, filtering,
    loss, gradient) is one compiled function; changing the parameters never recompiles.

    Args:
        filter_factory: a :class:`~gmjax.filters.Filter` whose ``params`` hold the tuned leaves
            (a relaxed reducer's thresholds, e.g. ``PCM(..., mode="soft")``'s ``rho`` and ``lam``,
            are leaves ``"reducer.rho"``, ``"reducer.lam"``; a hard threshold has gradient 0), or
            a factory ``params -> Filter`` taking a dict of traced scalars.
        scenario: the :class:`~gmjax.models.Scenario` to simulate.
        params0: name -> initial value (inside its bounds); with a Filter, each name a scalar
            floating leaf of ``filter.params``.
        loss: ``TuneScores -> ()``, e.g. :func:`armse_loss` or :func:`weighted_loss`.
        optimizer: an optax ``GradientTransformation`` (default ``optax.adam(0.05)``, in
            unconstrained units).
        n_runs: Monte Carlo runs per step.
        steps: optimiser steps.
        key: PRNG key (keyword-only).
        bounds: name -> ``(low, high)`` / :class:`Bounds` (default unbounded).
        resample: fresh runs every step (default) or common random numbers.
        ad: ``"forward"`` (``jax.jacfwd``: cheap for a few parameters, memory independent of the
            horizon) or ``"reverse"`` (``jax.grad``).
        progress: compilation notice and a progress bar (loss and parameters of each step) on stderr.

    Returns:
        A :class:`TuneResult`; ``plot_history(result.history)`` plots it.

    Raises:
        ValueError: bad arguments (naming them), or an initial value outside its bounds.
    """
    import optax

    if not callable(loss):
        raise ValueError("loss: expected a callable TuneScores -> scalar")
    if not isinstance(params0, Mapping) or not params0:
        raise ValueError(f"params0: expected a non-empty dict name -> value, got {params0!r}")
    if isinstance(filter_factory, Filter):
        filter_factory = _leaf_factory(filter_factory, params0)
    elif not callable(filter_factory):
        raise ValueError("filter_factory: expected a Filter or a callable params -> Filter")
    for name, arg in (("n_runs", n_runs), ("steps", steps)):
        if isinstance(arg, bool) or not isinstance(arg, int) or arg < 1:
            raise ValueError(f"{name}: must be a positive int, got {arg!r}")
    if ad not in ("forward", "reverse"):
        raise ValueError(f"ad: expected 'forward' or 'reverse', got {ad!r}")
    bounds = dict(bounds or {})
    unknown = sorted(set(bounds) - set(params0))
    if unknown:
        raise ValueError(f"bounds: names {unknown} are not in params0")
    names = sorted(params0)
    bnds = {n: _as_bounds(bounds.get(n), n) for n in names}
    for n in names:
        v = float(params0[n])
        if not math.isfinite(v) or not bnds[n].contains(v):
            raise ValueError(f"params0[{n!r}]: {v} is not strictly inside its bounds {tuple(bnds[n])}")
    optimizer = optax.adam(0.05) if optimizer is None else optimizer
    dtype = jnp.zeros(()).dtype
    u = jnp.asarray([bnds[n].to_unconstrained(float(params0[n])) for n in names], dtype)

    def constrained(u_vec):
        return {n: bnds[n].to_constrained(u_vec[i]) for i, n in enumerate(names)}

    def loss_and_flag_rate(scores):
        return loss(scores), jnp.mean(scores.flags.astype(dtype))

    def objective(u_vec, k):
        return study_loss(filter_factory(constrained(u_vec)), scenario, n_runs, k, loss_and_flag_rate)

    if ad == "forward":

        def value_and_grad(u_vec, k):
            def f(v):
                val, flag = objective(v, k)
                return val, (val, flag)

            g, (val, flag) = jax.jacfwd(f, has_aux=True)(u_vec)
            return val, flag, g
    else:

        def value_and_grad(u_vec, k):
            (val, flag), g = jax.value_and_grad(objective, has_aux=True)(u_vec, k)
            return val, flag, g

    def step_fn(u_vec, opt_state, k):
        val, flag, g_u = value_and_grad(u_vec, k)
        ok = jnp.isfinite(val) & jnp.all(jnp.isfinite(g_u))
        g_safe = jnp.where(ok, g_u, 0.0)
        updates, new_state = optimizer.update(g_safe, opt_state, u_vec)
        new_u = jnp.where(ok, optax.apply_updates(u_vec, updates), u_vec)
        new_state = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new_state, opt_state)
        # chain rule back to the constrained parameters: dL/dθ = (dL/du) / (dθ/du)
        jac = jnp.diagonal(jax.jacfwd(lambda v: jnp.stack([constrained(v)[n] for n in names]))(u_vec))
        g_theta = g_u / jac
        return new_u, new_state, val, flag, g_theta, ok

    opt_state = optimizer.init(u)
    step_jit = jax.jit(step_fn)
    bar = Progress(steps, desc="tune", unit="steps", enabled=progress)
    t0 = time.perf_counter()
    key0 = jax.random.fold_in(key, 0) if resample else key
    with bar.compiling("one optimiser step"):
        compiled = step_jit.lower(u, opt_state, key0).compile()
    compile_s = time.perf_counter() - t0

    losses, oks, flags, times = [], [], [], []
    p_hist: dict[str, list[float]] = {n: [] for n in names}
    g_hist: dict[str, list[float]] = {n: [] for n in names}
    for s in range(steps):
        k = jax.random.fold_in(key, s) if resample else key0
        theta = {n: float(v) for n, v in constrained(u).items()}
        t1 = time.perf_counter()
        u, opt_state, val, flag, g_theta, ok = compiled(u, opt_state, k)
        val = float(val)
        times.append(time.perf_counter() - t1)
        losses.append(val)
        oks.append(bool(ok))
        flags.append(float(flag))
        for i, n in enumerate(names):
            p_hist[n].append(theta[n])
            g_hist[n].append(float(g_theta[i]))
        ps = " ".join(f"{n}={theta[n]:.4g}" for n in names)
        bar.update(1, postfix=f"loss {val:.5g}  {ps}{'' if ok else '  (non-finite: update skipped)'}")
    history = TuneHistory(
        loss=np.asarray(losses),
        params={n: np.asarray(v) for n, v in p_hist.items()},
        grads={n: np.asarray(v) for n, v in g_hist.items()},
        ok=np.asarray(oks),
        flag_rate=np.asarray(flags),
        step_s=np.asarray(times),
    )
    final = {n: float(v) for n, v in constrained(u).items()}
    return TuneResult(final, history, compile_s)


def plot_history(history: TuneHistory, path: str | None = None, *, title: str | None = None) -> Any:
    """Plot the loss and every parameter against the step (matplotlib, imported lazily).

    Args:
        history: a :class:`TuneHistory`.
        path: save the figure there (PNG) when given.
        title: figure title.

    Returns:
        The matplotlib ``Figure``.
    """
    return plot_curves(history.loss, history.params, path, title=title, label_y=True)
