"""State-space models with additive Gaussian-mixture noises (docs/design.md §3)."""

from __future__ import annotations

from functools import partial
from typing import Any, Callable, NamedTuple, overload

import jax.numpy as jnp

from gmjax._jitcache import IdentityCache
from gmjax._types import Array, ArrayLike
from gmjax.inputs import StepInputs, step_inputs
from gmjax.mixture import GaussianMixture

__all__ = [
    "ModelParams",
    "LinearGaussianParams",
    "StateSpaceModel",
    "Scenario",
    "simulate",
    "call_convention",
    "as_step_fn",
    "wrap_angles",
    "CALL_CONVENTIONS",
    "inputs_from_times",
    "scenario_from_model",
]

CALL_CONVENTIONS = ("t", "u,t", "inputs")


def call_convention(fn: Callable, call: str = "t", name: str = "f") -> str:
    """How a model function is called, as the model's ``call`` says: ``"t"`` (``fn(x, t)``),
    ``"u,t"`` (``fn(x, u, t)`` with the control ``u``) or ``"inputs"`` (``fn(x, inputs)`` with the
    whole :class:`~gmjax.filters.StepInputs`: ``t``, ``dt``, ``control``, ``aux``).

    The convention is always given, never read from ``fn``'s signature; ``fn`` and ``name`` only
    name the function in the error.

    Raises:
        ValueError: an unknown ``call`` (``"auto"``, the arity sniffing of gmjax 0.2, included).
    """
    if call in CALL_CONVENTIONS:
        return call
    hint = (
        " ('auto', reading the arity, was removed: say how the functions are called)"
        if call == "auto"
        else ""
    )
    raise ValueError(
        f"call: expected one of {CALL_CONVENTIONS} for {name} ({getattr(fn, '__name__', fn)!r}), "
        f"got {call!r}{hint}: 't' for {name}(x, t), 'u,t' for {name}(x, u, t) with a control, "
        f"'inputs' for {name}(x, inputs)"
    )


def _call_hint(name: str, conv: str, error: TypeError) -> TypeError:
    """A ``TypeError`` from calling a model function, with the convention it was called by."""
    form = {"t": "(x, t)", "u,t": "(x, u, t)", "inputs": "(x, inputs)"}[conv]
    return TypeError(
        f"model.{name}: called as {name}{form} (call={conv!r}) and failed: {error}. A function with "
        "a control takes (x, u, t) and needs call='u,t'; one of the whole step inputs takes "
        "(x, inputs) and needs call='inputs'"
    )


_STATE_NOISE_SUPPORT = (
    "the single-Gaussian filters (KF, EKF, UKF, CKF, GHKF, SGKF, SCKF: at the predicted-from mean), "
    "the IMM (at each mode's mixed mean), the particle filter (per particle), rts_smoother and "
    "simulate / scenario_from_model"
)


def _call_noise(fn: Callable, noise: GaussianMixture, *args) -> GaussianMixture:
    """``fn(noise, inputs)`` or ``fn(noise, inputs, x)``, a wrong arity named in the error."""
    try:
        return fn(noise, *args)
    except TypeError as e:
        form, flag = ("(noise, inputs, x)", "True") if len(args) == 2 else ("(noise, inputs)", "False")
        raise TypeError(
            f"model.process_noise_at: called as process_noise_at{form} (state_dependent_noise="
            f"{flag}) and failed: {e}. A noise of the state takes (noise, inputs, x) and needs "
            "state_dependent_noise=True"
        ) from e


def _is_step_inputs(s: Any) -> bool:

    return isinstance(s, StepInputs)


@overload
def as_step_fn(fn: Callable, call: str = ..., name: str = ...) -> Callable: ...


@overload
def as_step_fn(fn: None, call: str = ..., name: str = ...) -> None: ...


@overload
def as_step_fn(fn: Callable | None, call: str = ..., name: str = ...) -> Callable | None: ...


def as_step_fn(fn: Callable | None, call: str = "t", name: str = "f") -> Callable | None:
    """``fn`` as ``g(x, s)`` where ``s`` is a :class:`~gmjax.filters.StepInputs` (or, for code that
    still passes a bare time, the time ``t``), called by the convention ``call`` (``"t"``, ``"u,t"``
    or ``"inputs"``, :func:`call_convention`).

    The returned function only dispatches on the Python type of ``s`` (at trace time); a
    ``TypeError`` from ``fn`` (e.g. a wrong arity for ``call``) is raised again with the convention
    it was called by. Wrapping twice is harmless.
    """
    if fn is None or getattr(fn, "_gmjax_step_fn", False):
        return fn
    conv = call_convention(fn, call, name)

    def arguments(s):
        if conv == "t":
            return (s.t if _is_step_inputs(s) else s,)
        if conv == "u,t":
            return (s.control, s.t) if _is_step_inputs(s) else (None, s)
        return (s if _is_step_inputs(s) else StepInputs(t=s),)

    def g(x, s):
        args = arguments(s)
        try:
            return fn(x, *args)
        except TypeError as e:
            raise _call_hint(name, conv, e) from e

    g._gmjax_step_fn = True  # type: ignore[attr-defined]
    g.__wrapped_model_fn__ = fn  # type: ignore[attr-defined]
    return g


def wrap_angles(y: Array, angle_dims: tuple[int, ...]) -> Array:
    """Wrap the components ``angle_dims`` of ``y (..., m)`` into ``[-pi, pi)`` (others unchanged)."""
    if not angle_dims:
        return y
    idx = jnp.asarray(angle_dims)
    wrapped = jnp.mod(y[..., idx] + jnp.pi, 2 * jnp.pi) - jnp.pi
    return y.at[..., idx].set(wrapped)


class ModelParams(NamedTuple):
    """The numeric part of a :class:`StateSpaceModel`: what a filter's ``params`` hold (a pytree).

    Each entry is a :class:`~gmjax.mixture.GaussianMixture`, or for single-Gaussian filters also a
    ``(mean, cov)`` pair (e.g. :class:`gmjax.filters.GaussianState`). Replace a leaf to vmap or
    differentiate a filter over it, e.g. ``params._replace(process_noise=q)``.
    """

    prior: GaussianMixture
    process_noise: GaussianMixture
    measurement_noise: GaussianMixture


class LinearGaussianParams(NamedTuple):
    """Parameters of :func:`gmjax.filters.kalman_filter`: ``x' = F x + v``, ``z = H x + w``, ``v ~ N(0, Q)``,
    ``w ~ N(0, R)``, ``x_0 ~ N(prior_mean, prior_cov)`` (all plain arrays, all differentiable)."""

    F: Array  # (d, d)
    H: Array  # (m, d)
    Q: Array  # (d, d)
    R: Array  # (m, m)
    prior_mean: Array  # (d,)
    prior_cov: Array  # (d, d)


class StateSpaceModel(NamedTuple):
    """``x_k = f(x_{k-1}, k) + v_k``, ``z_k = h(x_k, k) + w_k`` with GM noises.

    Time indexing: step ``k`` of :func:`gmjax.filters.run` calls ``f`` and ``h`` with the step's
    inputs (``inputs.t[k]``, ``inputs.dt[k]``, ``inputs.control[k]``): ``f`` maps the previous state
    to the state *at* ``t[k]`` (the index of the output state), ``h`` measures the state at ``t[k]``.

    Attributes:
        f: the transition, ``f(x (d,), t) -> (d,)``; or ``f(x, u, t)`` with a control input ``u``
            (``inputs.control``, ``call="u,t"``); or ``f(x, inputs)`` with the whole
            :class:`~gmjax.filters.StepInputs` (``call="inputs"``; e.g. to use ``inputs.dt``).
        h: the measurement function, same conventions (``h(x, t)``, ``h(x, u, t)``, ``h(x, inputs)``).
        process_noise: GM of ``v`` (dim ``d``); a single Gaussian is a 1-component mixture.
        measurement_noise: GM of ``w`` (dim ``m``).
        prior: GM of ``x_0`` (dim ``d``).
        f_jacobian, h_jacobian: optional, same call convention as ``f`` / ``h``, returning
            ``(d, d) / (m, d)``; default ``jax.jacfwd``.
        angle_dims: measurement components that are angles (radians): every filter wraps their
            innovations into ``[-pi, pi)`` and averages them on the circle.
        process_noise_at: optional ``(noise: GaussianMixture, inputs) -> GaussianMixture``, the
            step's process noise from the one in ``params`` (e.g. ``Q(dt)``; see
            :func:`gmjax.models.library.noise_scaler`). ``None``: the same noise every step.
            With ``state_dependent_noise=True`` it is ``(noise, inputs, x) -> GaussianMixture``:
            the noise also depends on the state ``x (d,)`` at the *start* of the step
            (``v_k ~ p(v | x_{k-1}, dt)``; see :meth:`noise_at` for where each filter evaluates it).
        call: how ``f``, ``h`` and their Jacobians are called: ``"t"`` (default, ``f(x, t)``),
            ``"u,t"`` (``f(x, u, t)``) or ``"inputs"`` (``f(x, inputs)``); checked when a filter
            is built, never read from the functions' signatures.
        state_dependent_noise: ``process_noise_at`` takes the state, ``(noise, inputs, x)``.
    """

    f: Callable[[Array, Array], Array]
    h: Callable[[Array, Array], Array]
    process_noise: GaussianMixture
    measurement_noise: GaussianMixture
    prior: GaussianMixture
    f_jacobian: Callable[[Array, Array], Array] | None = None
    h_jacobian: Callable[[Array, Array], Array] | None = None
    angle_dims: tuple[int, ...] = ()
    process_noise_at: Callable[..., GaussianMixture] | None = None
    call: str = "t"
    state_dependent_noise: bool = False

    def step_fns(self) -> tuple[Callable, Callable, Callable | None, Callable | None]:
        """``(f, h, f_jacobian, h_jacobian)`` as ``g(x, inputs)`` (see :func:`as_step_fn`)."""
        return (
            as_step_fn(self.f, self.call, "f"),
            as_step_fn(self.h, self.call, "h"),
            as_step_fn(self.f_jacobian, self.call, "f_jacobian"),
            as_step_fn(self.h_jacobian, self.call, "h_jacobian"),
        )

    def noise_at(self, noise: GaussianMixture, inputs: Any, x: Array | None = None) -> GaussianMixture:
        """The step's process noise: ``process_noise_at(noise, inputs)``, or ``noise`` unchanged.

        For a state-dependent ``process_noise_at(noise, inputs, x)``, ``x (d,)`` is the state the
        step starts from. Where it is evaluated: the KF and EKF at the mean they predict from
        (exact for the linearised filter: ``P' = F P F^T + Q(m)``); the sigma-point filters (UKF,
        CKF, GHKF, SGKF, SCKF) also at that mean, not per sigma point (so ``E[Q(x)]`` is
        approximated by ``Q(E[x])``); the IMM at each mode's mixed mean; the particle filter at
        every particle (exact); :func:`~gmjax.filters.rts_smoother` at each filtered mean, as the
        forward filter did; :func:`simulate` at the true previous state. The Gaussian-sum filters
        (GSF, IMM-GSF, AGSSCKF, the seed 004 bank) and the Gaussian-sum smoother do not support
        it and raise.

        Raises:
            ValueError: a state-dependent noise called without ``x`` (a filter that does not
                support it).
        """
        if self.process_noise_at is None:
            return noise
        if self.state_dependent_noise:
            if x is None:
                raise ValueError(
                    "model.process_noise_at: depends on the state (noise, inputs, x), but this filter "
                    f"evaluates the process noise without a state; supported by {_STATE_NOISE_SUPPORT}"
                )
            if not _is_step_inputs(inputs):
                inputs = StepInputs(t=inputs)
            return _call_noise(self.process_noise_at, noise, inputs, x)
        if not _is_step_inputs(inputs):
            return noise
        return _call_noise(self.process_noise_at, noise, inputs)

    @property
    def params(self) -> ModelParams:
        """The noises and the prior as a :class:`ModelParams` pytree (the functions stay here)."""
        return ModelParams(self.prior, self.process_noise, self.measurement_noise)

    @property
    def state_dim(self) -> int:
        return self.prior.dim

    @property
    def measurement_dim(self) -> int:
        return self.measurement_noise.dim


class Scenario(NamedTuple):
    """A model the filter assumes plus the *true* simulator, the horizon and the paper's settings.

    The truth evolves as ``x_t = truth_f(x_{t-1}, t) + v_t`` with ``v_t = sample_process_noise(key, t)``
    and is observed as ``z_t = truth_h(x_t, t) + w_t`` with ``w_t = sample_measurement_noise(key, t)``
    for ``t = 1 .. n_steps``; ``x_0 = sample_initial(key)``. The true noises may differ from the
    mixtures in ``model`` (Gamma, glint, ...), which are what the filters assume.
    :func:`scenario_from_model` builds one from a model in one call.

    Attributes:
        name: short identifier (``gmjax study NAME``).
        model: the :class:`StateSpaceModel` given to the filters.
        n_steps: ``T``.
        sample_initial: ``key -> (d,)``.
        sample_process_noise: ``(key, t) -> (d,)`` (``(key, inputs)`` with ``noise_takes_inputs``;
            ``(key, inputs, x_prev)`` when also ``model.state_dependent_noise``).
        sample_measurement_noise: ``(key, t) -> (m,)`` (likewise).
        truth_f, truth_h: true dynamics / measurement function (default: the model's), in the
            model's call convention (``model.call``).
        position_dims: indices of the position components (for position RMSE / CEP).
        description: one paragraph, with the paper reference and every value we had to choose.
        inputs: per-step :class:`~gmjax.filters.StepInputs` with a leading ``T`` axis (irregular
            times ``t``, ``dt``, controls); ``None``: times ``1..T``.
        noise_takes_inputs: the samplers take the step's :class:`~gmjax.filters.StepInputs`
            instead of the time ``t`` (e.g. noise that depends on ``dt``).
    """

    name: str
    model: StateSpaceModel
    n_steps: int
    sample_initial: Callable[[Array], Array]
    sample_process_noise: Callable[[Array, ArrayLike], Array]
    sample_measurement_noise: Callable[[Array, ArrayLike], Array]
    truth_f: Callable[[Array, Array], Array] | None = None
    truth_h: Callable[[Array, Array], Array] | None = None
    position_dims: tuple[int, ...] | None = None
    description: str = ""
    inputs: Any = None
    noise_takes_inputs: bool = False


def inputs_from_times(times: ArrayLike, t0: float = 0.0, control: Any = None) -> Any:
    """:class:`~gmjax.filters.StepInputs` for measurements at ``times (T,)``: ``t = times``,
    ``dt = diff([t0, *times])`` and an optional ``control`` with a leading ``T`` axis.

    Raises:
        ValueError: times that are not 1-D, not finite or not increasing (from ``t0``).
    """
    import numpy as np

    times_np = np.asarray(times, float)
    if times_np.ndim != 1 or times_np.size == 0 or not np.all(np.isfinite(times_np)):
        raise ValueError(f"times: expected a non-empty finite 1-D array, got shape {times_np.shape}")
    dts = np.diff(np.concatenate([[float(t0)], times_np]))
    if np.any(dts <= 0):
        bad = int(np.argmax(dts <= 0))
        raise ValueError(f"times: must increase strictly from t0={t0} (first bad step {bad})")
    dtype = jnp.zeros(()).dtype
    return StepInputs(t=jnp.asarray(times_np, dtype), dt=jnp.asarray(dts, dtype), control=control)


def simulate(scenario: Scenario, key: Array, inputs: Any = None) -> tuple[Array, Array, Any]:
    """Simulate one trajectory.

    Args:
        scenario: the scenario.
        key: PRNG key.
        inputs: per-step :class:`~gmjax.filters.StepInputs` (default ``scenario.inputs``).

    Returns:
        ``(xs (T+1, d) with xs[0] = x_0, zs (T, m), ts)``: ``ts`` is the ``(T,)`` times ``1..T`` when
        the scenario has no inputs, else the :class:`~gmjax.filters.StepInputs` (pass either to
        :func:`gmjax.filters.run`).

    Called eagerly, the simulation is a ``jax.jit`` kept per scenario object: only the first call on a
    scenario compiles.
    """
    import jax

    from gmjax._validate import is_concrete

    inputs = scenario.inputs if inputs is None else inputs
    if is_concrete(key, inputs, scenario.model):  # eager: one compiled program per scenario
        program = _EAGER_SIMULATIONS.get((scenario,), lambda: jax.jit(partial(_simulate, scenario)))
        return program(key, inputs)
    return _simulate(scenario, key, inputs)


_EAGER_SIMULATIONS = IdentityCache(maxsize=32)


def _simulate(scenario: Scenario, key: Array, inputs: Any) -> tuple[Array, Array, Any]:
    import jax

    model = scenario.model
    f = as_step_fn(scenario.truth_f or model.f, model.call, "truth_f")
    h = as_step_fn(scenario.truth_h or model.h, model.call, "truth_h")
    k0, kv, kw = jax.random.split(key, 3)
    x0 = scenario.sample_initial(k0)
    T = scenario.n_steps
    steps = step_inputs(T, inputs)
    by_inputs = scenario.noise_takes_inputs
    by_state = by_inputs and model.state_dependent_noise  # v_k ~ p(v | x_{k-1}, inputs)

    def step(x, xs):
        inp, kvt, kwt = xs
        arg = inp if by_inputs else inp.t
        v = (
            scenario.sample_process_noise(kvt, arg, x)
            if by_state
            else scenario.sample_process_noise(kvt, arg)
        )
        x = f(x, inp) + v
        z = h(x, inp) + scenario.sample_measurement_noise(kwt, arg)
        return x, (x, z)

    _, (xs, zs) = jax.lax.scan(step, x0, (steps, jax.random.split(kv, T), jax.random.split(kw, T)))
    return jnp.concatenate([x0[None], xs]), zs, (steps.t if inputs is None else steps)


def scenario_from_model(
    model: StateSpaceModel,
    n_steps: int,
    *,
    name: str = "model",
    inputs: Any = None,
    sample_initial: Callable[[Array], Array] | None = None,
    sample_process_noise: Callable | None = None,
    sample_measurement_noise: Callable | None = None,
    position_dims: tuple[int, ...] | None = None,
    description: str = "",
) -> Scenario:
    """A :class:`Scenario` whose truth is the model itself, in one call.

    Defaults: ``x_0`` from ``model.prior``, the process noise from the model's mixture at each step
    (through ``process_noise_at``, so ``Q(dt)`` with irregular times, and at the previous true
    state for a state-dependent noise), the measurement noise from its mixture. Pass any sampler
    to replace one (e.g. a glint sampler, :func:`gmjax.models.noise.glint`); custom samplers take
    ``(key, inputs)`` (a process-noise sampler of a state-dependent model ``(key, inputs, x_prev)``).

    Args:
        model: the model the filters assume (and, by default, the truth).
        n_steps: ``T``.
        inputs: per-step :class:`~gmjax.filters.StepInputs` (e.g. :func:`inputs_from_times`).
    """
    from gmjax import mixture as gmm

    if isinstance(n_steps, bool) or not isinstance(n_steps, int) or n_steps < 1:
        raise ValueError(f"n_steps: must be a positive int, got {n_steps!r}")
    if inputs is not None:
        inputs = step_inputs(n_steps, inputs)

    def draw(gm, key):
        return gmm.sample(gm, key, 1)[0]

    return Scenario(
        name=name,
        model=model,
        n_steps=n_steps,
        sample_initial=sample_initial or (lambda key: draw(model.prior, key)),
        sample_process_noise=sample_process_noise
        or (lambda key, inp, x=None: draw(model.noise_at(model.process_noise, inp, x), key)),
        sample_measurement_noise=sample_measurement_noise
        or (lambda key, inp: draw(model.measurement_noise, key)),
        position_dims=position_dims,
        description=description,
        inputs=inputs,
        noise_takes_inputs=True,
    )
