"""Kalman filter for linear / affine models (FilterPy's ``KalmanFilter``; Joseph-form update).

``local_kf(F, H)`` for Gaussian sum filters, ``build_kf(model)`` for an affine model (``F_t``, ``H_t``
are the Jacobians of ``f``, ``h``), and ``kalman_filter(F, H, Q, R, m0, P0)`` from arrays.
"""

from __future__ import annotations

from typing import Callable

import jax.numpy as jnp
import numpy as np

from gmjax import mixture as gmm
from gmjax._types import Array, ArrayLike, PRNGKey
from gmjax.filters._core import (
    GaussianState,
    LocalFilter,
    check_model,
    from_local,
    gaussian_state_init,
    local_step_info,
)
from gmjax.filters._linearized import affine_parts, as_time_fn, linearized_filter
from gmjax.filters.base import Filter, StepInputs
from gmjax.models.base import LinearGaussianParams, StateSpaceModel

__all__ = ["LinearGaussianParams", "local_kf", "build_kf", "kalman_filter"]


def local_kf(F: ArrayLike | Callable[[Array], Array], H: ArrayLike | Callable[[Array], Array]) -> LocalFilter:
    """Kalman filter for ``x' = F x + v``, ``z = H x + w`` (noise means allowed).

    Args:
        F: ``(d, d)`` transition matrix, or a callable ``t -> (d, d)``.
        H: ``(m, d)`` measurement matrix, or a callable ``t -> (m, d)``.

    Returns:
        A :class:`LocalFilter` over :class:`GaussianState`.

    Raises:
        ValueError: non-square ``F``, ``H`` whose column count differs from ``F``'s size, or
            non-finite entries.
    """
    Ff = as_time_fn("F", F)
    Hf = as_time_fn("H", H)
    if not callable(F) and not callable(H):
        Fa, Ha = np.shape(F), np.shape(H)
        if Fa[0] != Fa[1]:
            raise ValueError(f"F: must be square (d, d), got {Fa}")
        if Ha[1] != Fa[0]:
            raise ValueError(f"H: expected shape (m, {Fa[0]}) to match F, got {Ha}")

    def f_lin(m, t):
        Fm = Ff(t).astype(m.dtype)
        return Fm @ m, Fm

    def h_lin(m, t):
        Hm = Hf(t).astype(m.dtype)
        return Hm @ m, Hm

    return linearized_filter(f_lin, h_lin)


def build_kf(model: StateSpaceModel) -> Filter:
    """Kalman filter for an affine model (``f``, ``h`` affine in ``x``), model level.

    ``F_t`` and ``H_t`` are the Jacobians of ``f(., t)`` and ``h(., t)`` (exact for affine maps);
    the offsets come from evaluating ``f`` and ``h`` themselves. GM noises and a GM prior are
    moment-matched (see :func:`gmjax.filters.from_local`). For a non-affine model use
    :func:`build_ekf` (this filter would then be an EKF linearised at 0, which is wrong).
    """
    check_model(model)
    f, h, _, _ = model.step_fns()
    return from_local(model, linearized_filter(affine_parts(f), affine_parts(h), model.angle_dims))


def kalman_filter(
    F: ArrayLike, H: ArrayLike, Q: ArrayLike, R: ArrayLike, prior_mean: ArrayLike, prior_cov: ArrayLike
) -> Filter:
    """A time-invariant Kalman filter built from arrays; ``params`` is a :class:`LinearGaussianParams`.

    The update is the Joseph form of :func:`local_kf`. Replace ``filter.params`` (or pass
    ``params=`` to :func:`gmjax.filters.run`) to vmap or differentiate over ``F``, ``H``, ``Q``,
    ``R`` or the prior.

    Raises:
        ValueError: shapes that do not fit together, naming the argument.
    """
    params = LinearGaussianParams(*(jnp.asarray(a) for a in (F, H, Q, R, prior_mean, prior_cov)))
    d = params.F.shape[0] if params.F.ndim == 2 else -1
    m = params.H.shape[0] if params.H.ndim == 2 else -1
    expected = {"F": (d, d), "H": (m, d), "Q": (d, d), "R": (m, m), "prior_mean": (d,), "prior_cov": (d, d)}
    for name, shape in expected.items():
        if getattr(params, name).shape != shape or min(shape) < 1:
            raise ValueError(
                f"{name}: expected shape {shape} (F is (d, d) and H is (m, d)), got "
                f"{getattr(params, name).shape}"
            )

    def local(p: LinearGaussianParams) -> LocalFilter:
        return linearized_filter(lambda m_, t: (p.F @ m_, p.F), lambda m_, t: (p.H @ m_, p.H))

    def init(p: LinearGaussianParams, prior=None, *, key: PRNGKey | None = None) -> GaussianState:
        del key
        if prior is None:
            return gaussian_state_init(p.prior_mean, p.prior_cov)
        return gaussian_state_init(*gmm.moments(prior))

    def predict(p: LinearGaussianParams, state, inputs: StepInputs, *, key: PRNGKey | None = None):
        del key
        return local(p).predict(state, inputs.t, jnp.zeros_like(state.mean), p.Q)

    def update(p: LinearGaussianParams, state, z, inputs: StepInputs, *, key: PRNGKey | None = None):
        del key
        loc = local(p)
        new, info = loc.update(state, z, inputs.t, jnp.zeros(p.R.shape[0], state.mean.dtype), p.R)
        return new, local_step_info(loc, new, info, z)

    return Filter(init, predict, update, params)
