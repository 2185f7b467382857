"""Sparse-grid (Smolyak Gauss–Hermite) quadrature Kalman filter (seed 002 §II-C).

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

__all__ = ["local_sgkf", "build_sgkf"]


def local_sgkf(
    f: StepFn, h: StepFn, level: int = 2, growth: str = "linear", angle_dims: tuple[int, ...] = ()
) -> LocalFilter:
    """Sparse-grid (Smolyak Gauss–Hermite) quadrature KF (seed 002 §II-C)."""
    quadrature.smolyak(1, level, growth)  # validate eagerly
    return local_sigma(f, h, lambda d, dtype: quadrature.smolyak(d, level, growth, dtype=dtype), angle_dims)


def build_sgkf(model: StateSpaceModel, level: int = 2, growth: str = "linear") -> Filter:
    """Model-level sparse-grid quadrature KF (GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    f, h, _, _ = model.step_fns()
    return from_local(model, local_sgkf(f, h, level, growth, model.angle_dims))
