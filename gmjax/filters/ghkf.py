"""Gauss–Hermite Kalman filter: tensor rule with ``order^d`` points (seed 002 eqs 35–38).

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

__all__ = ["local_ghkf", "build_ghkf"]


def local_ghkf(f: StepFn, h: StepFn, order: int = 3) -> LocalFilter:
    """Gauss–Hermite KF: tensor rule with ``order^d`` points (seed 002 eqs 35–38)."""
    quadrature.gauss_hermite(1, order)  # validate eagerly
    return local_sigma(f, h, lambda d, dtype: quadrature.gauss_hermite(d, order, dtype=dtype))


def build_ghkf(model: StateSpaceModel, order: int = 3) -> Filter:
    """Model-level Gauss–Hermite KF (GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    return from_local(model, local_ghkf(model.f, model.h, order))
