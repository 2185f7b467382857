"""Cluster-merge reduction, GMRCM (Xu et al. 2019 = seed 003, Algorithm 1 steps 4–8).

Per call (one filter step):

* **Step 4(2), low-weight rule** (§2.3: "drop components whose weight was very small for two
  consecutive steps, threshold 0.01"): a :class:`GMRCMState` carried by the filter holds, for every
  input slot, the number of consecutive previous steps its lineage had weight below the threshold.
  A component whose weight is below the threshold now and was below it in the previous
  ``low_steps - 1`` steps is dropped and the rest are renormalised.
* **Step 4(1), large-covariance rule**: Algorithm 1 reads "(1) 1.5 times the mean; if larger,
  return it as an iteration item of the next step", and §2.1 says components with a large variance
  are kept out of the clustering by a threshold. We read: a component whose covariance trace (on
  the clustering dimensions) exceeds ``large_factor`` × the mean trace of the live components is
  passed through unmerged.
* **Steps 5–7**: the confidence range ``λ`` in ``[0.5, 3]`` (§4.1) minimising the EISE
  ``Σ_c ∫ (f_c - q_c)² + α lg N'`` (eq 10; grid + Newton on the relaxation,
  :mod:`gmjax.reduction.eise`), the upper-triangular judgment matrix (eqs 4–6) and the
  re-assignment of shared components (eqs 7–9; the subset case by seed 003's H2, "absorb").
* **Step 8**: moment-preserving merge of every cluster (eqs 16–18).

**State contract.** ``new_state.low_count[o]`` is the consecutive-low count of output slot ``o``:
for a merged cluster, the smallest count among its members (a cluster is "low for two steps" only
if all its members were). The filter expands each output component into its children (prediction
with ``L`` process-noise terms, update with ``J`` measurement-noise terms) and must give each child
its parent's count, e.g. ``jnp.repeat(state.low_count, L * J)`` in the same slot order as the
mixture, before the next call. A fresh state (:meth:`GMRCM.init`) is all zeros.
"""

from __future__ import annotations

import sys
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from gmjax import _validate
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array
from gmjax.mixture import GaussianMixture, sanitize
from gmjax.reduction import _util
from gmjax.reduction.base import ReductionInfo, make_info, reduces_with_state
from gmjax.reduction.eise.search import ConfidenceSearch, SearchOptions, _SearchSettings
from gmjax.reduction.merge import merge_labels
from gmjax.reduction.pcm import checked_search, search_aux

if sys.version_info >= (3, 11):
    from typing import Unpack
else:  # pragma: no cover - Python 3.10
    from typing_extensions import Unpack

__all__ = ["GMRCMState", "gmrcm", "GMRCM", "init_state"]


class GMRCMState(NamedTuple):
    """What the filter carries between calls of :func:`gmrcm`.

    Attributes:
        low_count: ``(K,)`` int32, consecutive previous steps each slot's lineage had a weight below
            the threshold (aligned with the mixture's slots).
    """

    low_count: Array


def init_state(capacity: int) -> GMRCMState:
    """A fresh state (no history) for mixtures of ``capacity`` slots."""
    return GMRCMState(jnp.zeros((capacity,), jnp.int32))


def gmrcm(
    gm: GaussianMixture,
    state: GMRCMState | None = None,
    *,
    lam: Any = None,
    weight_threshold: Any = 0.01,
    low_steps: int = 2,
    large_factor: Any = 1.5,
    capacity: int | None = None,
    key: jax.Array | None = None,
    **search: Unpack[SearchOptions],
) -> tuple[GaussianMixture, GMRCMState, ReductionInfo]:
    """Cluster-merge reduction of seed 003 (Algorithm 1 steps 4–8).

    Args:
        gm: input mixture, capacity ``K``.
        state: the :class:`GMRCMState` carried by the filter (``None``: a fresh one).
        lam: a fixed ``λ``; ``None`` searches it over ``lambda_range`` (§4.1: ``[0.5, 3]``).
        weight_threshold: the low-weight threshold (§2.3: 0.01), compared with the weights as given.
        low_steps: static number of consecutive low steps that drops a component (2).
        large_factor: covariance-trace factor of step 4(1) (1.5); ``inf`` disables the rule.
        capacity: static output capacity (default ``K``).
        key: unused.
        **search: the confidence search (:class:`~gmjax.reduction.eise.SearchOptions`, see
            :func:`gmjax.reduction.eise.search_confidence`), from seed 003's values
            (:meth:`~gmjax.reduction.eise.ConfidenceSearch.seed003`): ``alpha`` of eq 10 (§4.2:
            0.3), ``lambda_range`` (§4.1: ``(0.5, 3)``), ``temperature`` (0.25), ``grid_size`` (11),
            ``newton_steps`` (8), ``tol`` (1e-6), ``range_scale`` (0.5; the confidence scope is
            ``range_scale · λσ``, :mod:`gmjax.reduction.clustering`) and the static clustering
            ``dims`` (default all).

    Returns:
        ``(reduced, new_state, info)``; ``new_state`` is aligned with the output slots (see the
        module docstring), ``info.cost`` is the EISE, ``info.aux`` holds the search entries of
        :func:`gmjax.reduction.pcm.pcm` plus ``n_dropped`` (low-weight rule) and ``n_passed``
        (large-covariance rule).

    Raises:
        ValueError: for a bad concrete mixture, state or option, naming the argument.
        TypeError: for a keyword that is neither an argument above nor a search setting.
    """
    del key
    (weight_threshold, large_factor), bad = _util.replace_nans((weight_threshold, 0.01), (large_factor, 1.5))
    _validate.validate_mixture(gm)
    confidence, lam, bad_search = checked_search(gm, lam, ConfidenceSearch.seed003(), search, caller="gmrcm")
    _validate.validate_nonneg(weight_threshold, "weight_threshold")
    _validate.validate_nonneg(large_factor, "large_factor")
    low_steps = _validate.validate_count(low_steps, "low_steps", 1, 2**31 - 1)
    cap = _validate.validate_capacity(capacity, gm)
    K = gm.capacity
    if state is None:
        state = init_state(K)
    if not isinstance(state, GMRCMState) or jnp.shape(state.low_count) != (K,):
        raise ValueError(f"state: expected a GMRCMState with low_count of shape ({K},)")
    out = _gmrcm_core(
        gm, state, lam, confidence, weight_threshold, large_factor, low_steps=low_steps, capacity=cap
    )
    return _util.unchanged_if_nan(_util.either(bad, bad_search), gm, out, state_init=init_state)


@partial(jax.jit, static_argnames=("low_steps", "capacity"))
def _gmrcm_core(gm, state, lam, search, weight_threshold, large_factor, *, low_steps, capacity):
    K = gm.capacity
    cap = capacity
    dtype = gm.means.dtype

    # Step 4(2): consecutive low-weight rule, then renormalise the rest.
    w = jnp.where(gm.mask, gm.weights, 0.0)
    low = gm.mask & (w < weight_threshold)
    count = jnp.where(low, state.low_count.astype(jnp.int32) + 1, 0)
    drop = gm.mask & (count >= low_steps)
    heaviest = jnp.arange(K) == jnp.argmax(jnp.where(gm.mask, w, -jnp.inf))
    drop = jnp.where(jnp.all(drop | ~gm.mask), drop & ~heaviest, drop)  # never empty the mixture
    keep = gm.mask & ~drop
    total = jnp.sum(w)
    kept_mass = jnp.sum(jnp.where(keep, w, 0.0))
    scale = jnp.where(kept_mass > 0, total / jnp.where(kept_mass > 0, kept_mass, 1.0), 1.0)
    work = sanitize(GaussianMixture(w * scale, gm.means, gm.covs, keep))

    # Step 4(1): large covariances pass through unclustered.
    dims = search.dims
    covs_c = work.covs if dims is None else work.covs[:, jnp.asarray(dims)][:, :, jnp.asarray(dims)]
    tr = jnp.trace(covs_c, axis1=-2, axis2=-1)
    n_keep = jnp.sum(keep.astype(dtype))
    mean_tr = jnp.sum(jnp.where(keep, tr, 0.0)) / jnp.maximum(n_keep, 1.0)
    big = keep & (tr > large_factor * mean_tr)
    cl_mask = keep & ~big
    cl_mask = jnp.where(jnp.any(cl_mask), cl_mask, keep)  # everything large: cluster all
    big = keep & ~cl_mask
    to_cluster = sanitize(work._replace(mask=cl_mask))
    n_ref = jnp.sum(cl_mask.astype(jnp.int32))

    # Steps 5–7: search λ, judgment matrix, clusters, re-assignment; EISE of eq 10.
    res = search(to_cluster, lam)  # searched (lam None) or at the given λ

    # Step 8: moment-preserving merge (eqs 16–18); passed-through slots are their own cluster.
    slots = jnp.arange(K, dtype=jnp.int32)
    labels = jnp.where(big, slots, res.labels)
    labels = jnp.where(keep, labels, -1)
    merged = merge_labels(work, labels, K, "moment")
    out, labels_out, overflow, _ = _util.finalize(gm, merged, labels, cap)

    # New state: a cluster's count is the smallest of its members' counts.
    big_int = jnp.iinfo(jnp.int32).max
    seg = jnp.where(labels_out >= 0, labels_out, cap)
    out_count = jax.ops.segment_min(jnp.where(keep, count, big_int), seg, num_segments=cap + 1)[:cap]
    out_count = jnp.where(out.mask, out_count, 0).astype(jnp.int32)

    aux = search_aux(res, n_ref)
    aux["n_dropped"] = jnp.sum(drop.astype(jnp.int32))
    aux["n_passed"] = jnp.sum(big.astype(jnp.int32))
    info = make_info(
        gm, out, labels_out, pruned_mass=total - kept_mass, overflow=overflow, cost=res.eise, aux=aux
    )
    return out, GMRCMState(out_count), info


@pytree_dataclass
class GMRCM(_SearchSettings):
    """Config for :func:`gmrcm` (static: sizes and step counts; the rest are traced): :func:`gmrcm`'s
    arguments, its search settings included (seed 003's values, as in
    :meth:`~gmjax.reduction.eise.ConfidenceSearch.seed003`).

    A stateful :class:`~gmjax.reduction.Reducer`: :meth:`init` gives a fresh state (no low-weight
    history), :meth:`reduce` reduces with the state a filter carries, and ``GMRCM()(gm)`` reduces
    from a fresh state.
    """

    # seed 003's scope, α and τ; the other search settings as _SearchSettings declares them
    lambda_range: Any = (0.5, 3.0)
    alpha: Any = 0.3
    temperature: Any = 0.25
    lam: Any = None
    weight_threshold: Any = 0.01
    large_factor: Any = 1.5
    low_steps: int = static_field(2)
    capacity: int | None = static_field(None)

    def init(self, capacity: int) -> GMRCMState:
        """A fresh state for mixtures of ``capacity`` slots."""
        return init_state(capacity)

    reduce = reduces_with_state(gmrcm)

    def __call__(
        self, gm: GaussianMixture, *, key: jax.Array | None = None
    ) -> tuple[GaussianMixture, ReductionInfo]:
        out, _, info = self.reduce(gm, None, key=key)
        return out, info
