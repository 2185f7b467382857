"""Mixture reduction: pruning, merging and the classical reducers as fixed-capacity kernels.

Every reducer is a function ``name(gm, ..., *, key=None) -> (GaussianMixture, ReductionInfo)`` and a
frozen config (static sizes, dynamic thresholds) that satisfies the :class:`Reducer` protocol.
All run under ``jit`` and ``vmap``; ``info.labels`` maps every input slot to its output slot.

:class:`PruneThreshold`, :class:`PruneCensored` and :class:`PCM` carry a relaxation (a static
``mode``: ``"hard"``, ``"soft"``, ``"straight_through"``, and a traced temperature) that makes
them differentiable in their thresholds; the shared primitives (soft step, gates, gated pruning,
soft memberships, the soft split gate) are in :mod:`gmjax.reduction.relax`.
"""

from gmjax.reduction._base import Reducer as Reducer
from gmjax.reduction._base import ReductionInfo as ReductionInfo
from gmjax.reduction._base import make_info as make_info
from gmjax.reduction._brute import BruteForce as BruteForce
from gmjax.reduction._brute import brute_force as brute_force
from gmjax.reduction._gmrc import GMRC as GMRC
from gmjax.reduction._gmrc import gmrc as gmrc
from gmjax.reduction._greedy import Runnalls as Runnalls
from gmjax.reduction._greedy import Salmond as Salmond
from gmjax.reduction._greedy import West as West
from gmjax.reduction._greedy import runnalls as runnalls
from gmjax.reduction._greedy import runnalls_cost as runnalls_cost
from gmjax.reduction._greedy import salmond as salmond
from gmjax.reduction._greedy import salmond_cost as salmond_cost
from gmjax.reduction._greedy import west as west
from gmjax.reduction._ise_greedy import COWA as COWA
from gmjax.reduction._ise_greedy import Williams as Williams
from gmjax.reduction._ise_greedy import cowa as cowa
from gmjax.reduction._ise_greedy import williams as williams
from gmjax.reduction._kmeans import KMeans as KMeans
from gmjax.reduction._kmeans import kmeans as kmeans
from gmjax.reduction._kmeans import weighted_mahalanobis_sq as weighted_mahalanobis_sq
from gmjax.reduction._merge import merge_ci as merge_ci
from gmjax.reduction._merge import merge_labels as merge_labels
from gmjax.reduction._merge import merge_moment as merge_moment
from gmjax.reduction._prune import PruneCensored as PruneCensored
from gmjax.reduction._prune import PruneThreshold as PruneThreshold
from gmjax.reduction._prune import PruneTop as PruneTop
from gmjax.reduction._prune import censored_count as censored_count
from gmjax.reduction._prune import prune_censored as prune_censored
from gmjax.reduction._prune import prune_threshold as prune_threshold
from gmjax.reduction._prune import prune_top as prune_top
from gmjax.reduction._refine import Refined as Refined
from gmjax.reduction._refine import ise_refine as ise_refine
from gmjax.reduction._vo_ma import VoMa as VoMa
from gmjax.reduction._vo_ma import vo_ma as vo_ma
from gmjax.reduction._clustering import gauss_cluster as gauss_cluster
from gmjax.reduction._eise import eise as eise
from gmjax.reduction._eise import onehot_membership as onehot_membership
from gmjax.reduction._eise import search_confidence as search_confidence
from gmjax.reduction._gmrcm import GMRCM as GMRCM
from gmjax.reduction._gmrcm import GMRCMState as GMRCMState
from gmjax.reduction._gmrcm import gmrcm as gmrcm
from gmjax.reduction._pcm import PCM as PCM
from gmjax.reduction._pcm import pcm as pcm
from gmjax.reduction import relax as relax
from gmjax.reduction.relax import MODES as MODES
from gmjax.reduction.relax import gated_prune as gated_prune

__all__ = [
    "Reducer",
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
    "eise",
    "onehot_membership",
    # costs
    "runnalls_cost",
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
