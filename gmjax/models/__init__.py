"""State-space models, true-noise simulators and the scenarios of the papers.

* :class:`StateSpaceModel`, :class:`Scenario`, :func:`simulate` (docs/design.md §3).
* :mod:`seed000`: the scalar measurement-jump system and the range-bearing target (seed 000 §IV).
* :mod:`seed001`: the 1-D Gamma-noise system (seed 001 §4.1).
* :mod:`seed003`: the §4.2 tracking scenarios (circular motion, step manoeuvre) and their CS/CT IMM models.
* :mod:`seed004`: Table I synthetic Models 1-3 and the Table II UWB noise models (seed 004 §V).
* :mod:`pcrb_scenarios`: the linear system, the 1-D benchmark and the satellite of seed 002 §V.
* :mod:`noise`: true-noise samplers (glint, Laplace, mixtures).
"""

from gmjax.models import noise as noise
from gmjax.models import pcrb_scenarios as pcrb_scenarios
from gmjax.models import seed000 as seed000
from gmjax.models import seed001 as seed001
from gmjax.models import seed003 as seed003
from gmjax.models import seed004 as seed004
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
    "seed000",
    "seed001",
    "seed003",
    "seed004",
    "pcrb_scenarios",
]
