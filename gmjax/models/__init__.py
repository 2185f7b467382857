"""State-space models and true-noise samplers (docs/design.md §3).

* :class:`StateSpaceModel`, :class:`ModelParams`, :class:`Scenario`, :func:`simulate`;
  :class:`LinearGaussianParams` (the arrays of a linear Gaussian model, :func:`gmjax.filters.kalman_filter`'s params).
* :func:`scenario_from_model`, :func:`inputs_from_times`: a scenario in one call, irregular times.
* :mod:`noise`: true-noise samplers (glint, Laplace, mixtures).
* :mod:`library`: motion and measurement models (constant velocity/acceleration, Singer, turns,
  range/bearing/elevation/range-rate) with ``Q(dt)``, and :func:`library.state_space_model`.

The papers' scenarios are in :mod:`gmjax.scenarios`, one module per system.
"""

from gmjax.models import library as library
from gmjax.models import noise as noise
from gmjax.models.base import LinearGaussianParams as LinearGaussianParams
from gmjax.models.base import ModelParams as ModelParams
from gmjax.models.base import Scenario as Scenario
from gmjax.models.base import StateSpaceModel as StateSpaceModel
from gmjax.models.base import as_step_fn as as_step_fn
from gmjax.models.base import inputs_from_times as inputs_from_times
from gmjax.models.base import scenario_from_model as scenario_from_model
from gmjax.models.base import simulate as simulate
from gmjax.models.base import wrap_angles as wrap_angles

__all__ = [
    "ModelParams",
    "LinearGaussianParams",
    "StateSpaceModel",
    "Scenario",
    "simulate",
    "noise",
    "library",
    "as_step_fn",
    "inputs_from_times",
    "scenario_from_model",
    "wrap_angles",
]
