"""The one registry of component-level (local) filters, by name.

Gaussian sum filters, the IMM, the IMM-GSF and the AGSSCKF accept a local filter by name; every name
is accepted everywhere: ``kf`` (exact Jacobians of an affine model), ``ekf``, ``ukf``, ``ckf``,
``ghkf``, ``sgkf``, ``sckf``.
"""

from __future__ import annotations

from typing import Any, Callable

from gmjax.filters import ckf, ekf, ghkf, sckf, sgkf, ukf
from gmjax.filters._core import LocalFilter
from gmjax.filters._linearized import affine_parts, linearized_filter
from gmjax.models.base import StateSpaceModel

__all__ = ["LOCAL_FILTERS", "local_filter_for"]

LOCAL_FILTERS: dict[str, Callable[..., LocalFilter]] = {
    "kf": lambda m, **kw: linearized_filter(affine_parts(m.step_fns()[0]), affine_parts(m.step_fns()[1]),
                                            m.angle_dims),
    "ekf": lambda m, **kw: ekf.local_ekf(*m.step_fns(), m.angle_dims),
    "ukf": lambda m, **kw: ukf.local_ukf(*m.step_fns()[:2], **kw, angle_dims=m.angle_dims),
    "ckf": lambda m, **kw: ckf.local_ckf(*m.step_fns()[:2], m.angle_dims),
    "ghkf": lambda m, **kw: ghkf.local_ghkf(*m.step_fns()[:2], **kw, angle_dims=m.angle_dims),
    "sgkf": lambda m, **kw: sgkf.local_sgkf(*m.step_fns()[:2], **kw, angle_dims=m.angle_dims),
    "sckf": lambda m, **kw: sckf.local_sckf(*m.step_fns()[:2], m.angle_dims),
}


def local_filter_for(model: StateSpaceModel, name: str, **kwargs: Any) -> LocalFilter:
    """The component-level filter ``name`` built from ``model.f`` and ``model.h``.

    Raises:
        ValueError: an unknown name, listing the known ones.
    """
    if name not in LOCAL_FILTERS:
        raise ValueError(f"local: unknown local filter {name!r}; expected one of {sorted(LOCAL_FILTERS)}")
    return LOCAL_FILTERS[name](model, **kwargs)
