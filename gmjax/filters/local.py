"""The one registry of component-level (local) filters, by name.

Gaussian sum filters, the IMM, the IMM-GSF and the AGSSCKF accept a local filter by name; every name
is accepted everywhere: ``kf`` (exact Jacobians of an affine model), ``ekf``, ``ukf``, ``ckf``,
``ghkf``, ``sgkf``, ``sckf``.
"""

from __future__ import annotations

from typing import Any, Callable

from gmjax.filters import ckf, ekf, ghkf, sckf, sgkf, ukf
from gmjax.filters._core import LocalFilter, gaussian_moments
from gmjax.filters._linearized import affine_parts, linearized_filter
from gmjax.models.base import StateSpaceModel

__all__ = ["LOCAL_FILTERS", "local_filter_for", "LocalFilter", "gaussian_moments"]


def _fh(m: StateSpaceModel) -> tuple[Callable, Callable]:
    f, h, _, _ = m.step_fns()
    return f, h


def _kf(m: StateSpaceModel, **kw: Any) -> LocalFilter:
    f, h = _fh(m)
    return linearized_filter(affine_parts(f), affine_parts(h), m.angle_dims)


def _ekf(m: StateSpaceModel, **kw: Any) -> LocalFilter:
    f, h, fj, hj = m.step_fns()
    return ekf.local_ekf(f, h, fj, hj, m.angle_dims)


LOCAL_FILTERS: dict[str, Callable[..., LocalFilter]] = {
    "kf": _kf,
    "ekf": _ekf,
    "ukf": lambda m, **kw: ukf.local_ukf(*_fh(m), **{**kw, "angle_dims": m.angle_dims}),
    "ckf": lambda m, **kw: ckf.local_ckf(*_fh(m), m.angle_dims),
    "ghkf": lambda m, **kw: ghkf.local_ghkf(*_fh(m), **{**kw, "angle_dims": m.angle_dims}),
    "sgkf": lambda m, **kw: sgkf.local_sgkf(*_fh(m), **{**kw, "angle_dims": m.angle_dims}),
    "sckf": lambda m, **kw: sckf.local_sckf(*_fh(m), m.angle_dims),
}


def local_filter_for(model: StateSpaceModel, name: str, **kwargs: Any) -> LocalFilter:
    """The component-level filter ``name`` built from ``model.f`` and ``model.h``.

    Raises:
        ValueError: an unknown name, listing the known ones.
    """
    if name not in LOCAL_FILTERS:
        raise ValueError(f"local: unknown local filter {name!r}; expected one of {sorted(LOCAL_FILTERS)}")
    return LOCAL_FILTERS[name](model, **kwargs)
