"""Extended Kalman filter: first-order linearisation at the mean (seed 000 eqs 3–18 per component).
"""

from __future__ import annotations

from gmjax._types import StepFn
from gmjax.filters._core import (
    LocalFilter,
    check_model,
    from_local,
)
from gmjax.filters._linearized import linearized_filter, with_jacobian
from gmjax.filters.base import Filter
from gmjax.models.base import StateSpaceModel

__all__ = ["local_ekf", "build_ekf"]


def local_ekf(f: StepFn, h: StepFn, f_jacobian: StepFn | None = None, h_jacobian: StepFn | None = None) -> LocalFilter:
    """Extended Kalman filter (first-order linearisation at the mean; seed 000 eqs 3–18 per component).

    Args:
        f: ``f(x (d,), t) -> (d,)``.
        h: ``h(x (d,), t) -> (m,)``.
        f_jacobian, h_jacobian: optional ``(x, t) -> (d, d)`` / ``(m, d)``; default
            ``jax.jacfwd`` of ``f`` / ``h`` in ``x``.

    Returns:
        A :class:`LocalFilter` over :class:`GaussianState`.
    """
    return linearized_filter(with_jacobian(f, f_jacobian), with_jacobian(h, h_jacobian))


def build_ekf(model: StateSpaceModel) -> Filter:
    """Extended Kalman filter for a model (Jacobians from the model or ``jax.jacfwd``).

    GM noises and a GM prior are moment-matched (see :func:`gmjax.filters.from_local`).
    """
    check_model(model)
    return from_local(
        model, local_ekf(model.f, model.h, model.f_jacobian, model.h_jacobian)
    )
