"""State-space models and true-noise samplers (docs/design.md §3).

* :class:`StateSpaceModel`, :class:`ModelParams`, :class:`Scenario`, :func:`simulate`.
* :mod:`noise`: true-noise samplers (glint, Laplace, mixtures).

The papers' scenarios are in :mod:`gmjax.scenarios`, one module per system.
"""

from gmjax.models import noise as noise
from gmjax.models.base import ModelParams as ModelParams
from gmjax.models.base import Scenario as Scenario
from gmjax.models.base import StateSpaceModel as StateSpaceModel
from gmjax.models.base import simulate as simulate

__all__ = [
    "ModelParams",
    "StateSpaceModel",
    "Scenario",
    "simulate",
    "noise",
]
