"""Cubature Kalman filter: third-degree spherical-radial rule, ``2d`` points (seed 001 eq 7).

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

__all__ = ["local_ckf", "build_ckf"]


def local_ckf(f: StepFn, h: StepFn) -> LocalFilter:
    """Cubature KF: third-degree spherical-radial rule, ``2d`` points (seed 001 eq 7)."""
    return local_sigma(f, h, lambda d, dtype: quadrature.cubature(d, dtype=dtype))


def build_ckf(model: StateSpaceModel) -> Filter:
    """Model-level cubature KF (GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    return from_local(model, local_ckf(model.f, model.h))
