"""The optimisation loop of :func:`gmjax.fitting.fit`: the compiled optimiser step, convergence, the result.

:func:`~gmjax.fitting.fit` checks its arguments, builds (and caches) one compiled optax step on the
unconstrained values, runs it until the convergence test passes or the steps run out (skipping
non-finite steps, writing and resuming checkpoints), and returns a :class:`~gmjax.fitting.FitResult`
with its :class:`~gmjax.fitting.FitHistory`, which :func:`~gmjax.fitting.plot_history` draws.
"""

from __future__ import annotations

import os
import time
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._jitcache import CachedProgram, IdentityCache
from gmjax._plotting import plot_curves
from gmjax._progress import Progress
from gmjax._types import PRNGKey
from gmjax.filters.base import Filter
from gmjax.fitting._checkpoint import _fit_config, _FitLog, _read_fit_checkpoint, _write_fit_checkpoint
from gmjax.fitting._objectives import (
    Objective,
    _data_args,
    _is_multitarget,
    _is_multitarget_scenario,
    _value_fn,
    nll,
    study,
)
from gmjax.fitting._params import ParamView, param_view
from gmjax.models.base import Scenario
from gmjax.montecarlo._files import _remove_stale_tmp

_STEP_PROGRAMS = IdentityCache(maxsize=16)


def _step_program(
    filter, objective, scenario, optimizer, names, constraints
) -> tuple[CachedProgram, Callable]:
    """The compiled optimiser step ``(u, state, key, base, data) -> (u, state, loss, grad_max, ok,
    natural)`` and the optimiser's ``init``, kept per filter, objective, scenario and optimizer object."""
    import optax

    def make():
        opt = optax.with_extra_args_support(optimizer)
        value = _value_fn(filter, objective, scenario, names, constraints)

        def step(u, state, k, base, data):
            v, g = jax.value_and_grad(value)(u, k, base, data)
            leaves = jax.tree_util.tree_leaves(g)
            ok = jnp.isfinite(v) & jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))
            g_safe = jax.tree_util.tree_map(lambda x: jnp.where(ok, x, 0.0), g)
            updates, new_state = opt.update(
                g_safe, state, u, value=v, grad=g_safe, value_fn=lambda w: value(w, k, base, data)
            )
            new_u = jax.tree_util.tree_map(
                lambda a, b: jnp.where(ok, a, b), optax.apply_updates(u, updates), u
            )
            new_state = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new_state, state)
            gmax = jnp.max(jnp.stack([jnp.max(jnp.abs(x)) for x in leaves]))
            natural = ParamView(names, constraints, base).natural(u)
            return new_u, new_state, v, gmax, ok, natural

        return CachedProgram(jax.jit(step)), opt.init

    tag = (
        names,
        tuple(sorted(constraints.items())),
        objective.kind,
        objective.n_runs,
        objective.resample,
    )
    return _STEP_PROGRAMS.get((filter, objective.loss, scenario, optimizer), make, tag=tag)


# ----------------------------------------------------------------------------- the loop


class FitHistory(NamedTuple):
    """Step by step (NumPy; one row per step taken): ``loss``, ``grad_max`` (largest unconstrained
    gradient entry), ``ok`` (finite loss and gradient) and ``values`` (name -> natural value before the
    step)."""

    loss: np.ndarray
    grad_max: np.ndarray
    ok: np.ndarray
    values: dict[str, np.ndarray]


class FitResult(NamedTuple):
    """Outcome of :func:`fit`.

    Attributes:
        params: the filter's params with the fitted leaves (natural units); ``filter._replace(params=
            result.params)`` is the fitted filter.
        values: name -> fitted value (NumPy, natural units).
        loss: the objective at the start of the last step (for a converged fit, the final value's
            within ``ftol``); ``history.loss`` has every step's.
        history: a :class:`FitHistory`; ``plot_history`` of :mod:`gmjax.fitting` plots it.
        converged: the convergence test passed (module docstring); ``n_steps``: steps taken;
            ``n_skipped``: non-finite steps skipped.
        compile_s, run_s: seconds compiling the step and running the steps.
    """

    params: Any
    values: dict[str, np.ndarray]
    loss: float
    history: FitHistory
    converged: bool
    n_steps: int
    n_skipped: int
    compile_s: float
    run_s: float


def fit(
    filter: Filter,
    data: Any,
    objective: Objective | Callable | None = None,
    *,
    fit: Sequence[str] | str,
    key: PRNGKey,
    constraints: Mapping[str, Any] | None = None,
    optimizer: Any = None,
    steps: int = 200,
    gtol: float = 1e-8,
    ftol: float = 1e-12,
    params: Any = None,
    progress: bool = True,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = True,
    checkpoint_every: float = 10.0,
) -> FitResult:
    """Fit the leaves ``fit`` of ``filter.params`` to ``data`` by minimising ``objective``.

    Args:
        filter: any :class:`~gmjax.filters.Filter`.
        data: measurements ``zs (T, m)`` or a batch ``(B, T, m)``, or ``(zs, inputs)`` (inputs as
            :func:`gmjax.filters.run` takes them, shared by the batch or with a leading ``B`` axis);
            or a :class:`~gmjax.models.Scenario` for a study loss.
        objective: :func:`nll` (default with measurements), :func:`study` (default with a scenario:
            :func:`study` ``()``), or, with a scenario, a bare ``RunScores -> ()`` loss such as
            :func:`gmjax.montecarlo.armse_loss` ``()``.
        fit: names of the leaves to fit (see :func:`leaf_names`).
        key: PRNG key: the filter's key (particle filters) and the study's runs.
        constraints: name -> constraint, overriding the defaults (module docstring).
        optimizer: an optax transformation on the unconstrained values (default ``optax.lbfgs()``;
            ``optax.adam(0.05)`` with a resampled study).
        steps: at most this many steps.
        gtol, ftol: convergence tolerances (module docstring).
        params: start from these params (default ``filter.params``).
        progress: a progress bar (loss, steps/s) on stderr.
        checkpoint: a ``.npz`` path: the fit's state (unconstrained values, optimiser state, history)
            is written there atomically, with a checksum, every ``checkpoint_every`` seconds, at the
            end and when the fit is interrupted; the same call resumes from it (``resume``) and
            continues bit for bit as if never stopped. A checkpoint of another fit (leaves,
            constraints, objective, data, start, key, optimiser state's structure, gmjax version) is
            refused naming what differs; a corrupt one naming the cause.
        resume: continue from ``checkpoint`` when it exists (``False``: start again, overwriting it).
        checkpoint_every: seconds between checkpoint writes.

    Returns:
        A :class:`FitResult`.

    Raises:
        ValueError: bad arguments, naming them.
    """
    if not isinstance(filter, Filter):
        raise ValueError(f"filter: expected a gmjax Filter, got {type(filter).__name__}")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: must be a positive int, got {steps!r}")
    is_study = isinstance(data, Scenario) or _is_multitarget_scenario(data)
    if _is_multitarget_scenario(data) != _is_multitarget(filter) and is_study:
        raise ValueError(
            "data: a MultiTargetScenario goes with a GM-PHD filter (gmjax.multitarget.gm_phd; or gm_cphd, "
            f"gm_lmb) and a Scenario with a single-target filter; got {type(data).__name__} for this filter"
        )
    if objective is None:
        objective = study() if is_study else nll()
    elif not isinstance(objective, Objective):
        if not (is_study and callable(objective)):
            raise ValueError(
                "objective: expected fitting.nll() or fitting.study(...) (a bare loss needs a Scenario as data)"
            )
        objective = study(objective)
    if (objective.kind == "study") != is_study:
        want = "a Scenario" if objective.kind == "study" else "measurements (zs or (zs, inputs))"
        raise ValueError(f"data: the {objective.kind} objective needs {want}, got {type(data).__name__}")
    if not jnp.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key):
        raise ValueError(f"key: expected a PRNG key such as jax.random.key(0), got {key!r:.60}")
    view = param_view(filter.params if params is None else params, fit, constraints)
    resample = is_study and objective.resample
    if optimizer is None:
        optimizer = _default_optimizer(resample)
    program, opt_init = _step_program(
        filter, objective, data if is_study else None, optimizer, view.names, view.constraints
    )
    if not (isinstance(checkpoint_every, (int, float)) and checkpoint_every >= 0):
        raise ValueError(f"checkpoint_every: must be a number of seconds >= 0, got {checkpoint_every!r}")
    data_args = _data_args(data, objective, filter)
    u = view.unconstrained()
    state = opt_init(u)
    log = _FitLog(view.names)
    config = None
    if checkpoint is not None:
        config = _fit_config(view, objective, data, data_args, key, state)
        if resume and os.path.exists(checkpoint):
            u, state, log = _read_fit_checkpoint(checkpoint, config, u, state, view.names)
        else:
            _remove_stale_tmp(checkpoint)
    bar = Progress(steps, desc="fit", unit="steps", enabled=progress)
    with bar.compiling("one optimiser step"):
        compiled, compile_s = program.compile(u, state, key, view.params, data_args)
    if log.n_steps:
        bar.update(min(log.n_steps, steps), postfix=f"resumed from {checkpoint!s} at step {log.n_steps}")
    converged = log.n_steps > 0 and _converged(log.losses, log.gmaxs, log.oks, gtol, ftol)
    t1 = last_write = time.perf_counter()
    try:
        for s in range(log.n_steps, steps):
            if converged:
                break
            k = jax.random.fold_in(key, s) if resample else key
            u, state, v, gmax, ok, natural = compiled(u, state, k, view.params, data_args)
            log.append(float(v), float(gmax), bool(ok), natural)
            bar.update(
                1,
                postfix=f"loss {float(v):.8g}  |g| {float(gmax):.2g}{'' if ok else '  (non-finite: skipped)'}",
            )
            converged = _converged(log.losses, log.gmaxs, log.oks, gtol, ftol)
            if config is not None and time.perf_counter() - last_write >= checkpoint_every:
                _write_fit_checkpoint(checkpoint, config, u, state, log)
                last_write = time.perf_counter()
    finally:  # interrupted or done: what was computed is kept
        if config is not None and log.n_steps:
            _write_fit_checkpoint(checkpoint, config, u, state, log)
    run_s = time.perf_counter() - t1
    losses, gmaxs, oks, values = log.losses, log.gmaxs, log.oks, log.values
    final = view.params_at(u)
    final_values = {n: np.asarray(x) for n, x in view.natural(u).items()}
    history = FitHistory(
        loss=np.asarray(losses),
        grad_max=np.asarray(gmaxs),
        ok=np.asarray(oks),
        values={n: np.stack(v) for n, v in values.items()},
    )
    return FitResult(
        params=final,
        values=final_values,
        loss=losses[-1],
        history=history,
        converged=converged,
        n_steps=len(losses),
        n_skipped=int(np.sum(~history.ok)),
        compile_s=compile_s,
        run_s=run_s,
    )


def _default_optimizer(resample: bool) -> Any:
    import optax

    return _DEFAULT_OPTIMIZERS.setdefault(resample, optax.adam(0.05) if resample else optax.lbfgs())


_DEFAULT_OPTIMIZERS: dict[bool, Any] = {}  # one object each, so the compiled step is kept across fits


def _converged(losses: list[float], gmaxs: list[float], oks: list[bool], gtol: float, ftol: float) -> bool:
    if not oks[-1]:
        return False
    if gmaxs[-1] <= gtol:
        return True
    if len(losses) < 4 or not all(oks[-4:]):
        return False
    last = losses[-4:]
    scale = max(1.0, abs(last[-1]))
    return all(abs(a - b) <= ftol * scale for a, b in zip(last, last[1:]))


def plot_history(result: FitResult, path: str | None = None, *, title: str | None = None) -> Any:
    """Plot the loss curve and each scalar fitted value against the step (matplotlib, imported lazily)."""
    h = result.history
    scalars = {n: v for n, v in h.values.items() if v[0].size <= 4}
    loss_title = "loss" + (" (converged)" if result.converged else "")
    return plot_curves(h.loss, scalars, path, title=title, loss_title=loss_title)
