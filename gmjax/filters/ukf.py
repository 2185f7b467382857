"""Unscented Kalman filter (scaled unscented transform).

Built on the sigma-point core :func:`gmjax.filters._sigma.local_sigma`.
"""

from __future__ import annotations

from gmjax import quadrature
from gmjax._types import StepFn
from gmjax.filters._core import (
    LocalFilter,
    check_model,
    from_local,
)
from gmjax.filters._sigma import local_sigma
from gmjax.filters.base import Filter
from gmjax.models.base import StateSpaceModel

__all__ = ["local_ukf", "build_ukf"]


def local_ukf(
    f: StepFn,
    h: StepFn,
    alpha: float = 1.0,
    beta: float = 0.0,
    kappa: float | None = None,
    angle_dims: tuple[int, ...] = (),
) -> LocalFilter:
    """Unscented KF with the scaled UT (seed 002 eqs 27–32; defaults of :func:`quadrature.unscented`).

    FilterPy's ``MerweScaledSigmaPoints(d, alpha, beta, kappa)`` is the same point set.

    Args:
        f, h: transition and measurement functions ``(x, t) -> ...``.
        alpha, beta, kappa: scaled-UT parameters; ``kappa=None`` means ``3 - d``.

    Raises:
        ValueError: ``alpha <= 0`` or non-finite parameters (eagerly); ``d + lambda <= 0`` when
            the filter is first traced (the state dimension is known then).
    """
    quadrature.unscented(1, alpha, beta, 0.0 if kappa is None else max(float(kappa), 0.0))
    return local_sigma(
        f, h, lambda d, dtype: quadrature.unscented(d, alpha, beta, kappa, dtype=dtype), angle_dims
    )


def build_ukf(
    model: StateSpaceModel, alpha: float = 1.0, beta: float = 0.0, kappa: float | None = None
) -> Filter:
    """Model-level UKF (scaled UT; GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    quadrature.unscented(d, alpha, beta, kappa)  # validate eagerly
    f, h, _, _ = model.step_fns()
    return from_local(model, local_ukf(f, h, alpha, beta, kappa, model.angle_dims))
