"""Multi-target filtering: a batched, differentiable GM-PHD filter, scenarios and OSPA/GOSPA.

==================  ===========================================================================
module              contents
==================  ===========================================================================
``phd``             the GM-PHD filter (Vo & Ma 2006) as a :class:`gmjax.filters.Filter`, its
                    :func:`run` over padded measurement sets, state extraction (hard and relaxed)
``cphd``            the GM-CPHD filter (Vo, Vo & Cantoni 2007) under the same contract: the intensity
                    and the cardinality distribution, MAP state extraction (run it with :func:`run`)
``lmb``             the GM-LMB filter (Reuter, Vo, Vo & Dietmayer 2014) under the same contract:
                    labelled tracks (existence + Gaussian mixture), a Gibbs-sampled hypothesis
                    budget (Vo, Vo & Hoang 2017), labelled estimates
``hypotheses``      the LMB update's joint association hypotheses: Gibbs sampler, distinct rows, weights
``cardinality``     the CPHD's cardinality algebra in the log domain (ESFs, prediction, ``Upsilon``)
``scans``           padded measurement sets of any sizes (:func:`pad_scans`), their masks
``extraction``      state extraction, hard (Vo & Ma Table III) and relaxed
``relaxed``         :func:`RelaxedVoMa` (``VoMa(mode="soft")``): Vo–Ma with soft gates (differentiable)
``scenarios``       multi-target scenarios and their simulation (births, deaths, ``P_D``, clutter)
``metrics``         OSPA, GOSPA (with its decomposition) and a relaxed GOSPA, via an exact
                    jit-able assignment (Hungarian algorithm)
``tracks``          track metrics on labelled estimates (host-side NumPy): OSPA^(2) and label switches
``study``           a differentiable Monte Carlo study loss (mean relaxed GOSPA), for ``gmjax.fit``
==================  ===========================================================================
"""

from gmjax.multitarget import cphd as cphd
from gmjax.multitarget import hypotheses as hypotheses
from gmjax.multitarget import lmb as lmb
from gmjax.multitarget import metrics as metrics
from gmjax.multitarget import phd as phd
from gmjax.multitarget import relaxed as relaxed
from gmjax.multitarget import scenarios as scenarios
from gmjax.multitarget import study as study
from gmjax.multitarget import tracks as tracks
from gmjax.multitarget.cphd import CPHDParams as CPHDParams
from gmjax.multitarget.cphd import CPHDState as CPHDState
from gmjax.multitarget.cphd import gm_cphd as gm_cphd
from gmjax.multitarget.lmb import LMBParams as LMBParams
from gmjax.multitarget.lmb import LMBState as LMBState
from gmjax.multitarget.lmb import gm_lmb as gm_lmb
from gmjax.multitarget.metrics import GOSPA as GOSPA
from gmjax.multitarget.metrics import gospa as gospa
from gmjax.multitarget.metrics import linear_sum_assignment as linear_sum_assignment
from gmjax.multitarget.metrics import ospa as ospa
from gmjax.multitarget.metrics import soft_gospa as soft_gospa
from gmjax.multitarget.phd import Estimates as Estimates
from gmjax.multitarget.phd import PaddedScans as PaddedScans
from gmjax.multitarget.phd import PHDParams as PHDParams
from gmjax.multitarget.phd import PHDState as PHDState
from gmjax.multitarget.phd import extract as extract
from gmjax.multitarget.phd import gm_phd as gm_phd
from gmjax.multitarget.phd import pad_scans as pad_scans
from gmjax.multitarget.phd import run as run
from gmjax.multitarget.phd import soft_estimates as soft_estimates
from gmjax.multitarget.relaxed import RelaxedVoMa as RelaxedVoMa
from gmjax.multitarget.scenarios import MultiTargetScenario as MultiTargetScenario
from gmjax.multitarget.scenarios import bucket_capacity as bucket_capacity
from gmjax.multitarget.scenarios import clutter_capacity as clutter_capacity
from gmjax.multitarget.scenarios import crossing_targets as crossing_targets
from gmjax.multitarget.scenarios import range_bearing as range_bearing
from gmjax.multitarget.scenarios import simulate as simulate
from gmjax.multitarget.scenarios import vo_ma_linear as vo_ma_linear
from gmjax.multitarget.study import GospaLoss as GospaLoss
from gmjax.multitarget.study import gospa_loss as gospa_loss
from gmjax.multitarget.study import study_loss as study_loss
from gmjax.multitarget.tracks import LabelSwitches as LabelSwitches
from gmjax.multitarget.tracks import label_switches as label_switches
from gmjax.multitarget.tracks import ospa2 as ospa2

__all__ = [
    "metrics",
    "phd",
    "cphd",
    "lmb",
    "hypotheses",
    "tracks",
    "relaxed",
    "scenarios",
    "GOSPA",
    "gospa",
    "ospa",
    "soft_gospa",
    "linear_sum_assignment",
    "Estimates",
    "PHDParams",
    "PHDState",
    "extract",
    "gm_phd",
    "CPHDParams",
    "CPHDState",
    "gm_cphd",
    "LMBParams",
    "LMBState",
    "gm_lmb",
    "ospa2",
    "label_switches",
    "LabelSwitches",
    "pad_scans",
    "PaddedScans",
    "run",
    "soft_estimates",
    "RelaxedVoMa",
    "MultiTargetScenario",
    "bucket_capacity",
    "clutter_capacity",
    "crossing_targets",
    "range_bearing",
    "simulate",
    "vo_ma_linear",
    "study",
    "GospaLoss",
    "gospa_loss",
    "study_loss",
]
