"""State-space models with additive Gaussian-mixture noises (docs/design.md §3)."""

from __future__ import annotations

import inspect
from typing import Any, Callable, NamedTuple

import jax.numpy as jnp

from gmjax._types import Array, ArrayLike
from gmjax.mixture import GaussianMixture

__all__ = [
    "ModelParams",
    "StateSpaceModel",
    "Scenario",
    "simulate",
    "call_convention",
    "as_step_fn",
    "wrap_angles",
    "CALL_CONVENTIONS",
]

CALL_CONVENTIONS = ("t", "u,t", "inputs")


def call_convention(fn: Callable, call: str = "auto", name: str = "f") -> str:
    """How a model function is called: ``"t"`` (``fn(x, t)``), ``"u,t"`` (``fn(x, u, t)`` with the
    control ``u``) or ``"inputs"`` (``fn(x, inputs)`` with the whole
    :class:`~gmjax.filters.StepInputs`: ``t``, ``dt``, ``control``, ``aux``).

    ``call="auto"`` reads the arity once (when the model is checked, never inside ``jit``): three
    positional parameters mean ``"u,t"``, anything else ``"t"``.

    Raises:
        ValueError: an unknown ``call``.
    """
    if call != "auto":
        if call not in CALL_CONVENTIONS:
            raise ValueError(f"call: expected 'auto' or one of {CALL_CONVENTIONS}, got {call!r}")
        return call
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return "t"
    kinds = [p.kind for p in params]
    if inspect.Parameter.VAR_POSITIONAL in kinds:
        return "t"
    n_pos = sum(k in (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
                for k in kinds)
    return "u,t" if n_pos == 3 else "t"


def _is_step_inputs(s: Any) -> bool:
    from gmjax.filters.base import StepInputs

    return isinstance(s, StepInputs)


def as_step_fn(fn: Callable | None, call: str = "auto", name: str = "f") -> Callable | None:
    """``fn`` as ``g(x, s)`` where ``s`` is a :class:`~gmjax.filters.StepInputs` (or, for code that
    still passes a bare time, the time ``t``), whatever ``fn``'s :func:`call_convention`.

    The convention is resolved here, once; the returned function only dispatches on the Python type
    of ``s`` (at trace time). Wrapping twice is harmless.
    """
    if fn is None or getattr(fn, "_gmjax_step_fn", False):
        return fn
    conv = call_convention(fn, call, name)

    if conv == "t":
        def g(x, s):
            return fn(x, s.t if _is_step_inputs(s) else s)
    elif conv == "u,t":
        def g(x, s):
            return fn(x, s.control, s.t) if _is_step_inputs(s) else fn(x, None, s)
    else:
        def g(x, s):
            if _is_step_inputs(s):
                return fn(x, s)
            from gmjax.filters.base import StepInputs

            return fn(x, StepInputs(t=s))

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


class StateSpaceModel(NamedTuple):
    """``x_k = f(x_{k-1}, k) + v_k``, ``z_k = h(x_k, k) + w_k`` with GM noises.

    Time indexing: step ``k`` of :func:`gmjax.filters.run` calls ``f`` and ``h`` with the step's
    inputs (``inputs.t[k]``, ``inputs.dt[k]``, ``inputs.control[k]``): ``f`` maps the previous state
    to the state *at* ``t[k]`` (the index of the output state), ``h`` measures the state at ``t[k]``.

    Attributes:
        f: the transition, ``f(x (d,), t) -> (d,)``; or ``f(x, u, t)`` with a control input ``u``
            (``inputs.control``); or ``f(x, inputs)`` with the whole
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
        call: ``"auto"`` (by arity: 3 positional parameters mean ``(x, u, t)``, else ``(x, t)``),
            ``"t"``, ``"u,t"`` or ``"inputs"``; read once when a filter is built.
    """

    f: Callable[[Array, Array], Array]
    h: Callable[[Array, Array], Array]
    process_noise: GaussianMixture
    measurement_noise: GaussianMixture
    prior: GaussianMixture
    f_jacobian: Callable[[Array, Array], Array] | None = None
    h_jacobian: Callable[[Array, Array], Array] | None = None
    angle_dims: tuple[int, ...] = ()
    process_noise_at: Callable[[GaussianMixture, Any], GaussianMixture] | None = None
    call: str = "auto"

    def step_fns(self) -> tuple[Callable, Callable, Callable | None, Callable | None]:
        """``(f, h, f_jacobian, h_jacobian)`` as ``g(x, inputs)`` (see :func:`as_step_fn`)."""
        return (as_step_fn(self.f, self.call, "f"), as_step_fn(self.h, self.call, "h"),
                as_step_fn(self.f_jacobian, self.call, "f_jacobian"),
                as_step_fn(self.h_jacobian, self.call, "h_jacobian"))

    def noise_at(self, noise: GaussianMixture, inputs: Any) -> GaussianMixture:
        """The step's process noise: ``process_noise_at(noise, inputs)``, or ``noise`` unchanged."""
        if self.process_noise_at is None or not _is_step_inputs(inputs):
            return noise
        return self.process_noise_at(noise, inputs)

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

    Attributes:
        name: short identifier (``gmjax study NAME``).
        model: the :class:`StateSpaceModel` given to the filters.
        n_steps: ``T``.
        sample_initial: ``key -> (d,)``.
        sample_process_noise: ``(key, t) -> (d,)``.
        sample_measurement_noise: ``(key, t) -> (m,)``.
        truth_f, truth_h: true dynamics / measurement function (default: the model's).
        position_dims: indices of the position components (for position RMSE / CEP).
        description: one paragraph, with the paper reference and every value we had to choose.
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


def simulate(scenario: Scenario, key: Array) -> tuple[Array, Array, Array]:
    """Simulate one trajectory: ``(xs (T+1, d) with xs[0] = x_0, zs (T, m), ts (T,) = 1..T)``."""
    import jax
    import jax.numpy as jnp

    f = scenario.truth_f or scenario.model.f
    h = scenario.truth_h or scenario.model.h
    k0, kv, kw = jax.random.split(key, 3)
    x0 = scenario.sample_initial(k0)
    T = scenario.n_steps
    ts = jnp.arange(1, T + 1, dtype=jnp.int32)

    def step(x, inputs):
        t, kvt, kwt = inputs
        x = f(x, t) + scenario.sample_process_noise(kvt, t)
        z = h(x, t) + scenario.sample_measurement_noise(kwt, t)
        return x, (x, z)

    _, (xs, zs) = jax.lax.scan(step, x0, (ts, jax.random.split(kv, T), jax.random.split(kw, T)))
    return jnp.concatenate([x0[None], xs]), zs, ts
