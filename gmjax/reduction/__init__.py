"""Mixture reduction: pruning, merging and the classical reducers as fixed-capacity kernels.

Every reducer is a function ``name(gm, ..., *, key=None) -> (GaussianMixture, ReductionInfo)`` and a
frozen config (static sizes, dynamic thresholds) that satisfies the :class:`Reducer` protocol
(:mod:`gmjax.reduction.base`, docs/design.md §3). All run under ``jit`` and ``vmap``;
``info.labels`` maps every input slot to its output slot.

One public module per algorithm, over shared private engines:

=====================  ==============================================================================
module                 algorithm
=====================  ==============================================================================
``prune``              threshold, top-K and censored pruning (``PruneThreshold``, ``PruneTop``, ``PruneCensored``)
``merge``              moment-preserving and covariance-intersection merges, merge by labels
``runnalls``           Runnalls' KL-bound greedy merging (R-GMR)
``salmond``            Salmond's joining algorithm
``west``               West's (and enhanced West) smallest-weight merging
``williams``           Williams & Maybeck's greedy ISE reduction
``cowa``               constraint-optimised weight adaptation (COWA)
``gmrc``               Gaussian mixture reduction via clustering (GMRC, Schieferdecker & Huber)
``kmeans``             weighted k-means over components
``vo_ma``              Vo & Ma's GM-PHD pruning and merging
``brute_force``        exhaustive ISE-optimal partition (small K)
``refine``             ISE refinement of a reduced mixture by gradient descent
``clustering``         Gauss clustering with confidence ranges (Xu et al., PCM)
``eise``               the EISE cost and the confidence-range search (Xu et al.; a package:
                       ``ise``, ``relaxed``, ``newton``, ``search``)
``pcm``                prune-cluster-merge (Xu et al., PCM)
``gmrcm``              cluster-merge with a low-weight history (Xu et al., GMRCM; stateful)
``relax``              soft / straight-through relaxations behind the reducers' ``mode``
``step6``              seed 001's Step 6: pruning and three merge rules with per-slot history (stateful)
=====================  ==============================================================================

The package re-exports each module's function and config, so ``gmjax.reduction.runnalls`` is the
*function*; the module is ``importlib.import_module("gmjax.reduction.runnalls")`` (or
``from gmjax.reduction.runnalls import ...``).

:class:`PruneThreshold`, :class:`PruneCensored` and :class:`PCM` carry a relaxation (a static
``mode``: ``"hard"``, ``"soft"``, ``"straight_through"``, and a traced temperature) that makes
them differentiable in their thresholds; the shared primitives (soft step, gates, gated pruning,
soft memberships, the soft split gate) are in :mod:`gmjax.reduction.relax`.
"""

from gmjax.reduction import relax as relax
from gmjax.reduction.base import EmptyState as EmptyState
from gmjax.reduction.base import Reducer as Reducer
from gmjax.reduction.base import ReductionInfo as ReductionInfo
from gmjax.reduction.base import make_info as make_info
from gmjax.reduction.brute_force import BruteForce as BruteForce
from gmjax.reduction.brute_force import brute_force as brute_force
from gmjax.reduction.clustering import gauss_cluster as gauss_cluster
from gmjax.reduction.cowa import COWA as COWA
from gmjax.reduction.cowa import cowa as cowa
from gmjax.reduction.eise import ConfidenceSearch as ConfidenceSearch
from gmjax.reduction.eise import EISECriterion as EISECriterion
from gmjax.reduction.eise import eise as eise
from gmjax.reduction.eise import onehot_membership as onehot_membership
from gmjax.reduction.eise import search_confidence as search_confidence
from gmjax.reduction.gmrc import GMRC as GMRC
from gmjax.reduction.gmrc import gmrc as gmrc
from gmjax.reduction.gmrcm import GMRCM as GMRCM
from gmjax.reduction.gmrcm import GMRCMState as GMRCMState
from gmjax.reduction.gmrcm import gmrcm as gmrcm
from gmjax.reduction.kmeans import KMeans as KMeans
from gmjax.reduction.kmeans import kmeans as kmeans
from gmjax.reduction.kmeans import weighted_mahalanobis_sq as weighted_mahalanobis_sq
from gmjax.reduction.merge import merge_ci as merge_ci
from gmjax.reduction.merge import merge_labels as merge_labels
from gmjax.reduction.merge import merge_moment as merge_moment
from gmjax.reduction.pcm import PCM as PCM
from gmjax.reduction.pcm import pcm as pcm
from gmjax.reduction.prune import PruneCensored as PruneCensored
from gmjax.reduction.prune import PruneThreshold as PruneThreshold
from gmjax.reduction.prune import PruneTop as PruneTop
from gmjax.reduction.prune import censored_count as censored_count
from gmjax.reduction.prune import prune_censored as prune_censored
from gmjax.reduction.prune import prune_threshold as prune_threshold
from gmjax.reduction.prune import prune_top as prune_top
from gmjax.reduction.refine import Refined as Refined
from gmjax.reduction.refine import ise_refine as ise_refine
from gmjax.reduction.relax import MODES as MODES
from gmjax.reduction.relax import gated_prune as gated_prune
from gmjax.reduction.runnalls import Runnalls as Runnalls
from gmjax.reduction.runnalls import runnalls as runnalls
from gmjax.reduction.runnalls import runnalls_cost as runnalls_cost
from gmjax.reduction.salmond import Salmond as Salmond
from gmjax.reduction.salmond import salmond as salmond
from gmjax.reduction.salmond import salmond_cost as salmond_cost
from gmjax.reduction.step6 import Step6Merge as Step6Merge
from gmjax.reduction.step6 import Step6State as Step6State
from gmjax.reduction.vo_ma import VoMa as VoMa
from gmjax.reduction.vo_ma import vo_ma as vo_ma
from gmjax.reduction.west import West as West
from gmjax.reduction.west import west as west
from gmjax.reduction.williams import Williams as Williams
from gmjax.reduction.williams import williams as williams

__all__ = [
    "Reducer",
    "EmptyState",
    "ReductionInfo",
    "make_info",
    # relaxations (mode / temperature of the reducers)
    "relax",
    "MODES",
    "gated_prune",
    # primitives
    "merge_moment",
    "merge_ci",
    "merge_labels",
    "prune_threshold",
    "prune_top",
    "prune_censored",
    "censored_count",
    # reducers
    "runnalls",
    "west",
    "salmond",
    "williams",
    "cowa",
    "gmrc",
    "kmeans",
    "vo_ma",
    "brute_force",
    "ise_refine",
    "pcm",
    "gmrcm",
    # clustering and the confidence search of PCM / GMRCM (seeds 000, 003)
    "gauss_cluster",
    "search_confidence",
    "ConfidenceSearch",
    "EISECriterion",
    "eise",
    "onehot_membership",
    # costs
    "runnalls_cost",
    "Step6Merge",
    "Step6State",
    "salmond_cost",
    "weighted_mahalanobis_sq",
    # configs
    "PruneThreshold",
    "PruneTop",
    "PruneCensored",
    "Runnalls",
    "West",
    "Salmond",
    "Williams",
    "COWA",
    "GMRC",
    "KMeans",
    "VoMa",
    "BruteForce",
    "Refined",
    "PCM",
    "GMRCM",
    "GMRCMState",
]
