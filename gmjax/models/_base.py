"""State-space models with additive Gaussian-mixture noises (DESIGN §3)."""

from __future__ import annotations

from typing import Callable, NamedTuple

from gmjax._types import Array
from gmjax.mixture import GaussianMixture

__all__ = ["StateSpaceModel"]


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
    def state_dim(self) -> int:
        return self.prior.dim

    @property
    def measurement_dim(self) -> int:
        return self.measurement_noise.dim
