"""The papers' scenarios, one module per system, named by what it models.

Each module builds :class:`gmjax.models.Scenario` objects (the model the filters use, the true-noise
simulator, the horizon and the paper's settings) or, for the PCRB papers, :class:`gmjax.pcrb.PCRBModel`
objects; the paper, its section and its equation numbers are in each module's docstring.

=========================  ========================================================================
module                     what it models (paper)
=========================  ========================================================================
``jump_system``            scalar measurement-jump system, glint process noise (Xu et al., PCM; Table 7)
``glint_range_bearing``    range-bearing tracking of a manoeuvring target in glint noise (Xu et al., PCM; Table 8)
``gamma_system``           scalar system with Gamma process noise (Liu et al., AGSSCKF; Table 2)
``bearings_only``          two-sensor bearings-only tracking of a turning target (Liu et al.; Table 3)
``manoeuvring_target``     circular motion and step manoeuvre, IMM of CS and CT models (Xu et al. 2019, GMRCM)
``uwb_velocity``           random-walk velocity with GM noise: Models 1-3 and UWB ranging (Pishdad & Labeau)
``linear_system``          linear Gaussian system for the PCRB (Zhang et al.)
``growth_model``           univariate nonstationary growth model, the 1-D PCRB benchmark (Zhang et al.)
``satellite_pass``         a satellite tracked by a ground radar over one pass (Zhang et al.)
=========================  ========================================================================

Import a module and call its constructor, e.g.
``from gmjax.scenarios.jump_system import jump_system; scenario = jump_system()``.
"""

from gmjax.scenarios import bearings_only as bearings_only
from gmjax.scenarios import gamma_system as gamma_system
from gmjax.scenarios import glint_range_bearing as glint_range_bearing
from gmjax.scenarios import growth_model as growth_model
from gmjax.scenarios import jump_system as jump_system
from gmjax.scenarios import linear_system as linear_system
from gmjax.scenarios import manoeuvring_target as manoeuvring_target
from gmjax.scenarios import satellite_pass as satellite_pass
from gmjax.scenarios import uwb_velocity as uwb_velocity

__all__ = [
    "jump_system",
    "glint_range_bearing",
    "gamma_system",
    "bearings_only",
    "manoeuvring_target",
    "uwb_velocity",
    "linear_system",
    "growth_model",
    "satellite_pass",
]
