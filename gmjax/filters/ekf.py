"""Extended Kalman filter: first-order linearisation at the mean (seed 000 eqs 3–18 per component)."""

from __future__ import annotations

from gmjax._types import StepFn
from gmjax.filters._core import (
    LocalFilter,
    check_model,
    from_local,
)
from gmjax.filters._linearized import linearized_filter, with_jacobian
from gmjax.filters.base import Filter
from gmjax.models.base import StateSpaceModel, as_step_fn

__all__ = ["local_ekf", "build_ekf"]


def local_ekf(
    f: StepFn,
    h: StepFn,
    f_jacobian: StepFn | None = None,
    h_jacobian: StepFn | None = None,
    angle_dims: tuple[int, ...] = (),
) -> LocalFilter:
    """Extended Kalman filter (first-order linearisation at the mean; seed 000 eqs 3–18 per component).

    Args:
        f: ``f(x (d,), t) -> (d,)``.
        h: ``h(x (d,), t) -> (m,)``.
        f_jacobian, h_jacobian: optional ``(x, t) -> (d, d)`` / ``(m, d)``; default
            ``jax.jacfwd`` of ``f`` / ``h`` in ``x``.

    Returns:
        A :class:`LocalFilter` over :class:`GaussianState`.
    """
    f_step, h_step = as_step_fn(f), as_step_fn(h)
    f_lin = with_jacobian(f_step, as_step_fn(f_jacobian))
    h_lin = with_jacobian(h_step, as_step_fn(h_jacobian))
    return linearized_filter(f_lin, h_lin, tuple(angle_dims))


def build_ekf(model: StateSpaceModel) -> Filter:
    """Extended Kalman filter for a model (Jacobians from the model or ``jax.jacfwd``).

    GM noises and a GM prior are moment-matched (see :func:`gmjax.filters.from_local`).
    """
    check_model(model)
    return from_local(model, local_ekf(*model.step_fns(), model.angle_dims))
