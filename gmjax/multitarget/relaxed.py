"""The relaxed Vo–Ma pruning and merging for PHD intensities, differentiable in its thresholds:
``VoMa(mode="soft")`` of :mod:`gmjax.reduction.vo_ma` (its module docstring has the relaxation),
re-exported here under its 0.2 names (:func:`RelaxedVoMa`, :func:`relaxed_vo_ma`)."""

from gmjax.reduction.vo_ma import RelaxedVoMa as RelaxedVoMa
from gmjax.reduction.vo_ma import relaxed_vo_ma as relaxed_vo_ma

__all__ = ["RelaxedVoMa", "relaxed_vo_ma"]
