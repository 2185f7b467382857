"""Learn a filter's model from data: maximum likelihood or a study loss, any parameter, in one call.

:func:`fit` takes a filter, the data (measurement sequences, or a :class:`~gmjax.models.Scenario` to
simulate), an objective and the names of the leaves of ``filter.params`` to fit, and runs an optax
optimiser in a compiled step until the loss stops moving. Everything else in ``params`` is held fixed;
masks and integer leaves never reach ``jax.grad``.

**Which leaves.** ``fit=["model.measurement_noise", "reducer.threshold"]`` names leaves by their path in
``filter.params`` (attribute names joined by dots, sequence indices as numbers); a name selects every
differentiable leaf below it (a mixture's ``weights``, ``means`` and ``covs``, not its ``mask``).
:func:`leaf_names` lists the names a filter has.

**Constraints.** The optimiser works on unconstrained values ``u``; each fitted leaf is mapped into its
valid set (:data:`CONSTRAINTS`): a mixture's ``weights`` onto the simplex of its live components
(softmax of log-weights; the weights of an intensity that does not sum to 1, such as a GM-PHD's
birth, stay positive instead), its ``covs`` onto SPD matrices (log-Cholesky: ``C = L L^T`` with ``L``'s
diagonal ``exp(u_ii)``), ``means`` unconstrained, every other leaf positive (softplus) unless
``constraints={name: "real" | "positive" | "unit" | "simplex" | "stochastic" | "spd" | (low, high)}``
says otherwise; an IMM's ``transition`` matrix keeps its rows on the simplex (``"stochastic"``), a
Kalman filter's ``Q``, ``R`` and ``prior_cov`` stay SPD.
Results are returned in natural units.

**Objectives.** :func:`nll` (the default with measurements): the negative log-likelihood per step,
``-(1 / (B T)) Σ_b Σ_t StepInfo.loglik``, of one ``(T, m)`` or a batch ``(B, T, m)`` of sequences, for
every filter that reports ``loglik`` (KF/EKF/UKF/CKF, GSF, IMM, PF, ...). :func:`study` (the default with
a scenario): any loss of :mod:`gmjax.montecarlo` (``armse_loss``, ``anees_loss``, ...) on ``n_runs``
simulated runs, the same runs every step (common random numbers) unless ``resample``; for a GM-PHD
filter on a :class:`~gmjax.multitarget.MultiTargetScenario`, a per-run loss of
:mod:`gmjax.multitarget.study` such as the mean relaxed GOSPA ``gospa_loss(c=...)``.

**Convergence.** The default optimiser is ``optax.lbfgs()`` for a deterministic objective and
``optax.adam(0.05)`` with ``resample``. A fit has converged when the unconstrained gradient's largest
entry is below ``gtol`` or the loss changed by less than ``ftol`` (relative) in each of the last 3
steps; it then stops early. A step with a non-finite loss or gradient is skipped and counted.

**Resume.** With ``checkpoint=path`` the unconstrained values, the optimiser state and the history are
written atomically (with a checksum) every ``checkpoint_every`` seconds, at the end and on an
interruption; the same call resumes and continues bit for bit. :mod:`gmjax.tune`'s factory-based loop
(version 0.1) remains for its users; ``fit`` reaches the same thresholds through ``params``
(``fit="reducer.rho"``).
"""

from __future__ import annotations

import json
import os
import time
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._jitcache import CachedProgram, IdentityCache
from gmjax._plotting import plot_curves
from gmjax._progress import Progress
from gmjax._types import Array, PRNGKey
from gmjax._version import __version__
from gmjax.filters.base import Filter, StepInputs, run
from gmjax.models.base import Scenario
from gmjax.montecarlo.files import _digest, _read_npz, _remove_stale_tmp, _write_npz

__all__ = [
    "CONSTRAINTS",
    "Objective",
    "ParamView",
    "FitHistory",
    "FitResult",
    "nll",
    "study",
    "leaf_names",
    "param_view",
    "loss_fn",
    "fit",
    "plot_history",
]

CONSTRAINTS = ("real", "positive", "unit", "simplex", "stochastic", "spd")


# ----------------------------------------------------------------------------- leaves by name


def _name(path: tuple) -> str:
    parts = []
    for k in path:
        for attr in ("name", "key", "idx"):
            if hasattr(k, attr):
                parts.append(str(getattr(k, attr)))
                break
        else:  # pragma: no cover - other key types
            parts.append(str(k))
    return ".".join(parts)


def _is_float_leaf(leaf: Any) -> bool:
    if isinstance(leaf, (jax.Array, np.ndarray, np.generic)):
        return bool(jnp.issubdtype(leaf.dtype, jnp.floating))
    return isinstance(leaf, float)


def leaf_names(params: Any) -> list[str]:
    """The names :func:`fit` accepts for ``params``: every floating leaf's dotted path, in tree order."""
    return [_name(p) for p, leaf in jax.tree_util.tree_flatten_with_path(params)[0] if _is_float_leaf(leaf)]


# ----------------------------------------------------------------------------- constraints


def _softplus_inv(x: Array) -> Array:
    return x + jnp.log(-jnp.expm1(-x))


def _to_natural(kind: Any, u: Array, mask: Array | None) -> Array:
    if kind == "real":
        return u
    if kind == "positive":
        return jax.nn.softplus(u)
    if kind == "unit":
        return jax.nn.sigmoid(u)
    if isinstance(kind, tuple):
        lo, hi = kind
        return lo + (hi - lo) * jax.nn.sigmoid(u)
    if kind == "simplex":
        live = jnp.ones(u.shape, bool) if mask is None else mask
        logits = jnp.where(live, u, -jnp.inf)
        return jnp.where(live, jax.nn.softmax(logits), 0.0)
    if kind == "stochastic":  # each row on the simplex (a Markov matrix)
        return jax.nn.softmax(u, axis=-1)
    # spd: u is the log-Cholesky factor (..., d, d): strict lower triangle, log of the diagonal
    d = u.shape[-1]
    eye = jnp.eye(d, dtype=u.dtype)
    L = jnp.tril(u, -1) + eye * jnp.exp(jnp.diagonal(u, axis1=-2, axis2=-1))[..., None, :]
    return L @ jnp.swapaxes(L, -1, -2)


def _to_unconstrained(kind: Any, x: Array, mask: Array | None) -> Array:
    if kind == "real":
        return x
    if kind == "positive":
        return _softplus_inv(x)
    if kind == "unit":
        return jnp.log(x) - jnp.log1p(-x)
    if isinstance(kind, tuple):
        lo, hi = kind
        p = (x - lo) / (hi - lo)
        return jnp.log(p) - jnp.log1p(-p)
    if kind == "simplex":
        live = jnp.ones(x.shape, bool) if mask is None else mask
        return jnp.where(live, jnp.log(jnp.where(live, x, 1.0)), 0.0)
    if kind == "stochastic":
        return jnp.log(x)
    L = jnp.linalg.cholesky(x)
    d = x.shape[-1]
    eye = jnp.eye(d, dtype=x.dtype)
    return jnp.tril(L, -1) + eye * jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1))[..., None, :]


def _check_natural(kind: Any, name: str, x: np.ndarray, mask: np.ndarray | None) -> None:
    """Refuse a starting value outside the leaf's constraint (its unconstrained value would be NaN)."""
    live = np.ones(x.shape[:1], bool) if mask is None else np.asarray(mask)
    bad = None
    if kind == "positive" and not np.all(x > 0):
        bad = "must be > 0"
    elif kind == "unit" and not np.all((x > 0) & (x < 1)):
        bad = "must lie in (0, 1)"
    elif isinstance(kind, tuple) and not np.all((x > kind[0]) & (x < kind[1])):
        bad = f"must lie in ({kind[0]}, {kind[1]})"
    elif kind == "simplex" and not (np.all(x[live] > 0) and abs(x[live].sum() - 1) < 1e-6):
        bad = "must be > 0 on the live components and sum to 1"
    elif kind == "stochastic" and not (
        x.ndim >= 1 and np.all(x > 0) and np.allclose(x.sum(-1), 1.0, rtol=0.0, atol=1e-6)
    ):
        bad = "must be > 0 with every row summing to 1"
    elif kind == "spd" and not (
        x.ndim >= 2
        and x.shape[-1] == x.shape[-2]
        and np.allclose(x, np.swapaxes(x, -1, -2))
        and np.all(np.linalg.eigvalsh(x[live] if x.ndim == 3 else x) > 0)
    ):
        bad = "must be symmetric positive definite"
    if bad is not None:
        raise ValueError(f"fit: {name!r} starts at {x.tolist()!r:.120}, which {bad} (constraint {kind!r})")


_COVARIANCE_NAMES = ("covs", "cov", "Q", "R", "P0", "prior_cov")


def _default_constraint(name: str, value: np.ndarray, mask: np.ndarray | None) -> str:
    """``weights`` (and ``*probs``) that sum to 1: simplex; a mixture's weights that do not (an intensity,
    such as a PHD's birth: expected numbers): positive; a ``transition`` matrix whose rows sum to 1:
    stochastic; covariances (``covs``, ``cov``, ``Q``, ``R``, ``P0``, ``prior_cov``): SPD; ``means``:
    real; anything else: positive."""
    last = name.rsplit(".", 1)[-1]
    if last == "weights" or last.endswith("probs"):
        live = np.ones(value.shape, bool) if mask is None else np.asarray(mask, bool)
        return "simplex" if value.ndim == 1 and abs(float(np.sum(value[live])) - 1.0) < 1e-6 else "positive"
    if last == "transition" and value.ndim == 2 and np.allclose(value.sum(-1), 1.0, rtol=0.0, atol=1e-6):
        return "stochastic"
    if last in _COVARIANCE_NAMES and value.ndim >= 2:
        return "spd"
    return "real" if last == "means" else "positive"


def _as_constraint(c: Any, name: str) -> Any:
    if isinstance(c, str) and c in CONSTRAINTS:
        return c
    if isinstance(c, (tuple, list)) and len(c) == 2 and all(isinstance(v, (int, float)) for v in c):
        lo, hi = float(c[0]), float(c[1])
        if not lo < hi:
            raise ValueError(f"constraints[{name!r}]: need low < high, got {c!r}")
        return (lo, hi)
    raise ValueError(f"constraints[{name!r}]: expected one of {CONSTRAINTS} or (low, high), got {c!r}")


class ParamView(NamedTuple):
    """The fitted leaves of a params pytree and their constraints (see :func:`param_view`).

    Attributes:
        names: the fitted leaves' names, in tree order.
        constraints: name -> constraint (one of :data:`CONSTRAINTS` or ``(low, high)``).
        params: the params pytree the view was made from (everything not fitted is taken from it).
    """

    names: tuple[str, ...]
    constraints: dict[str, Any]
    params: Any

    def _leaves(self) -> tuple[list, Any, dict[str, int], dict[str, Any]]:
        flat, treedef = jax.tree_util.tree_flatten_with_path(self.params)
        index = {_name(p): i for i, (p, _) in enumerate(flat)}
        leaves = [leaf for _, leaf in flat]
        masks = {}
        for n in self.names:  # a mixture's weights are constrained on its live components
            parent = n.rsplit(".", 1)[0] + ".mask" if "." in n else "mask"
            masks[n] = leaves[index[parent]] if parent in index and n.endswith("weights") else None
        return leaves, treedef, index, masks

    def unconstrained(self, params: Any = None) -> dict[str, Array]:
        """``{name: u}``: the unconstrained values of the fitted leaves of ``params`` (default: the view's)."""
        view = self if params is None else self._replace(params=params)
        leaves, _, index, masks = view._leaves()
        return {
            n: _to_unconstrained(self.constraints[n], jnp.asarray(leaves[index[n]]), masks[n])
            for n in self.names
        }

    def natural(self, u: Mapping[str, Array]) -> dict[str, Array]:
        """``{name: value}`` in natural units for unconstrained ``u``."""
        _, _, _, masks = self._leaves()
        return {n: _to_natural(self.constraints[n], u[n], masks[n]) for n in self.names}

    def params_at(self, u: Mapping[str, Array]) -> Any:
        """The full params pytree with the fitted leaves at ``u`` (traceable)."""
        leaves, treedef, index, _ = self._leaves()
        leaves = list(leaves)
        for n, v in self.natural(u).items():  # in the leaf's dtype (an optimiser may promote u)
            leaves[index[n]] = v.astype(jnp.result_type(leaves[index[n]]))
        return jax.tree_util.tree_unflatten(treedef, leaves)


def param_view(
    params: Any, fit: Sequence[str] | str, constraints: Mapping[str, Any] | None = None
) -> ParamView:
    """Select the leaves of ``params`` named by ``fit`` (each a leaf's dotted path or a prefix of it).

    Raises:
        ValueError: a name that selects no floating leaf (the message lists the names there are), a bad
            constraint, or a starting value outside its constraint.
    """
    if isinstance(fit, str):
        fit = [fit]
    fit = list(fit)
    if not fit:
        raise ValueError("fit: name at least one leaf of filter.params to fit")
    available = leaf_names(params)
    names: list[str] = []
    for sel in fit:
        if not isinstance(sel, str):
            raise ValueError(f"fit: expected leaf names (str), got {sel!r}")
        hit = [n for n in available if n == sel or n.startswith(sel + ".")]
        if not hit:
            raise ValueError(
                f"fit: {sel!r} names no floating leaf of filter.params; the leaves are {available}"
            )
        names += [n for n in hit if n not in names]
    names = [n for n in available if n in names]  # tree order
    constraints = dict(constraints or {})
    unknown = [sel for sel in constraints if not any(n == sel or n.startswith(sel + ".") for n in names)]
    if unknown:
        raise ValueError(f"constraints: {unknown} name no fitted leaf (fitted: {names})")
    leaves, _, index, masks = ParamView(tuple(names), {}, params)._leaves()
    start = {n: np.asarray(leaves[index[n]], np.float64) for n in names}
    mask = {n: None if masks[n] is None else np.asarray(masks[n]) for n in names}
    chosen: dict[str, Any] = {}
    for n in names:
        rule = next((c for sel, c in constraints.items() if n == sel or n.startswith(sel + ".")), None)
        chosen[n] = _default_constraint(n, start[n], mask[n]) if rule is None else _as_constraint(rule, n)
        _check_natural(chosen[n], n, start[n], mask[n])
    return ParamView(tuple(names), chosen, params)


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
    from gmjax.multitarget.phd import PHDParams

    return isinstance(filter.params, PHDParams)


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
            "data: a MultiTargetScenario goes with a GM-PHD filter (gmjax.multitarget.gm_phd) and a "
            f"Scenario with a single-target filter; got {type(data).__name__} for this filter"
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
