"""State-space models with additive Gaussian-mixture noises (docs/design.md §3)."""

from __future__ import annotations

from typing import Callable, NamedTuple

from gmjax._types import Array, ArrayLike
from gmjax.mixture import GaussianMixture

__all__ = ["ModelParams", "StateSpaceModel", "Scenario", "simulate"]


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

    Attributes:
        f: ``f(x (d,), t) -> (d,)`` traceable transition.
        h: ``h(x (d,), t) -> (m,)`` traceable measurement function.
        process_noise: GM of ``v`` (dim ``d``); a single Gaussian is a 1-component mixture.
        measurement_noise: GM of ``w`` (dim ``m``).
        prior: GM of ``x_0`` (dim ``d``).
        f_jacobian, h_jacobian: optional ``(x, t) -> (d, d) / (m, d)``; default ``jax.jacfwd``.
    """

    f: Callable[[Array, Array], Array]
    h: Callable[[Array, Array], Array]
    process_noise: GaussianMixture
    measurement_noise: GaussianMixture
    prior: GaussianMixture
    f_jacobian: Callable[[Array, Array], Array] | None = None
    h_jacobian: Callable[[Array, Array], Array] | None = None

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
