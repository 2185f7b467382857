"""Gaussian sum filter: GM prior, GM process noise, GM measurement noise, any local filter, any reducer.

The prediction pairs every posterior component ``i`` (capacity ``K``) with every process-noise
component ``l`` (``L`` of them): ``x' = f(x, t) + v_l`` through the local filter, weight
``alpha_i * gamma_l`` (seed 000 eqs 4–8; seed 004 eqs 5–6). The update pairs every predicted
component with every measurement-noise component ``j`` (``J``): local update with noise
``N(r_j, R_j)``, weight ``phi * beta_j * N(z; z_hat, S)`` normalised in the log domain (seed 000
eqs 9–16; seed 004 eqs 7–9). The ``K·L·J`` updated components are then reduced back to ``K`` slots
by the reducer. The point estimate and covariance (eqs 17–18) are the moments of the *updated*
mixture, before reduction.

Overflow policy: the reducer's output is fitted to capacity ``K``; if more than ``K`` components
survive, the ``K`` heaviest are kept, renormalised, and ``StepInfo.flags.overflow`` is set. With
``reducer=None`` the reducer is :class:`gmjax.reduction.PruneTop` with ``num_out=K`` (nothing is
merged: the ``K`` heaviest are kept, and the step is flagged when anything is dropped), so a capacity
of at least ``K_0 (L J)^T`` gives the exact GSF over ``T`` steps.

Reducers follow the one contract (:class:`gmjax.reduction.Reducer`): the filter carries the reducer
state aligned with the posterior's ``K`` slots, every predicted / updated child inherits its
parent's entries (:func:`inherit`), and a stateful reducer (e.g. :class:`gmjax.reduction.GMRCM`)
must return exactly ``K`` slots.

The two Gaussian-sum kernels, :func:`gs_predict` and :func:`gs_update`, are shared with the IMM of
Gaussian sum filters, the AGSSCKF and the seed 004 bank.

Time indexing follows :func:`gmjax.filters.run`. A measurement holding a NaN is a predict-only step
(the ``J`` measurement-noise copies collapse to one).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp

from gmjax import metrics
from gmjax import mixture as gmm
from gmjax._types import Array, PRNGKey
from gmjax.filters._core import LocalFilter, check_model, is_missing
from gmjax.filters.base import Filter, StepFlags, StepInfo, StepInputs
from gmjax.filters.local import local_filter_for
from gmjax.mixture import GaussianMixture
from gmjax.models.base import ModelParams, StateSpaceModel

__all__ = [
    "GSFState",
    "GSFParams",
    "build_gsf",
    "local_filter_for",
    "concrete_n_active",
    "fit_capacity",
    "gs_predict",
    "gs_update",
    "inherit",
    "check_reducer",
]


class GSFState(NamedTuple):
    """State of a Gaussian sum filter.

    Attributes:
        mixture: the posterior (after ``update``: capacity ``K``; after ``predict``: ``K·L``).
        reducer_state: the reducer's state aligned with ``mixture``'s slots
            (:class:`~gmjax.reduction.EmptyState` for stateless reducers).
    """

    mixture: GaussianMixture
    reducer_state: Any


class GSFParams(NamedTuple):
    """Parameters of :func:`build_gsf`: the model's noises and prior, and the reducer config (whose
    thresholds are leaves: differentiate or tune them here)."""

    model: ModelParams
    reducer: Any


def check_reducer(reducer: Any) -> Any:
    """Validate a reducer at the API boundary (``None`` stays ``None``).

    Raises:
        ValueError: when ``reducer`` does not follow :class:`gmjax.reduction.Reducer`.
    """
    if reducer is None:
        return None
    if not (callable(getattr(reducer, "init", None)) and callable(getattr(reducer, "reduce", None))):
        raise ValueError(
            f"reducer: expected a gmjax.reduction reducer config with init(capacity) and "
            f"reduce(gm, state, *, key) (e.g. reduction.Runnalls(num_out=8)), got {reducer!r}"
        )
    return reducer


def fit_capacity(
    gm: GaussianMixture, capacity: int, *, heaviest_first: bool = False
) -> tuple[GaussianMixture, Array]:
    """Pad or truncate ``gm`` to ``capacity`` slots, keeping the heaviest; returns ``(gm, overflow)``.

    Truncation renormalises the kept weights; ``overflow`` is True when a live component was dropped.
    ``heaviest_first`` (static): ``gm``'s live slots already come first, heaviest first (ties: lower
    slot), as the pruners store them, so the first ``capacity`` slots are the ``top_k`` and truncation
    is a slice (the same values, without a second ``top_k``).
    """
    if gm.capacity <= capacity:
        return gmm.pad(gm, capacity), jnp.zeros((), bool)
    overflow = gmm.n_active(gm) > capacity
    if heaviest_first:
        kept = jax.tree_util.tree_map(lambda a: a[:capacity], gm)
    else:
        kept = gmm.top_k(gm, capacity)
    kept = jax.lax.cond(overflow, gmm.normalize, lambda g: g, kept)
    return kept, overflow


def inherit(state: Any, n_children: int) -> Any:
    """Repeat every slot's entries for its ``n_children`` children (slot ``i`` -> ``i*n .. i*n+n-1``)."""
    return jax.tree_util.tree_map(lambda a: jnp.repeat(a, n_children, axis=0), state)


def _noise_log_weights(noise: GaussianMixture) -> Array:
    """Normalised log weights ``(L,)`` of a noise mixture."""
    log_w = gmm.log_weights(noise)
    return log_w - logsumexp(log_w)


def gs_predict(local: LocalFilter, gm: GaussianMixture, t: Any, noise: GaussianMixture) -> GaussianMixture:
    """Gaussian-sum prediction: every component ``i`` × every noise component ``l`` (seed 000 eqs 4–8).

    Returns:
        The ``K·L`` predicted components (child ``i*L + l``), weights ``alpha_i gamma_l``.
    """

    def one(mean, cov, qm, qP):
        return local.moments(local.predict(local.init(mean, cov), t, qm, qP))

    pair = jax.vmap(jax.vmap(one, (None, None, 0, 0)), (0, 0, None, None))
    means, covs = pair(gm.means, gm.covs, noise.means, noise.covs)  # (K, L, d), (K, L, d, d)
    log_w = gmm.log_weights(gm)[:, None] + _noise_log_weights(noise)[None, :]
    mask = gm.mask[:, None] & noise.mask[None, :]
    d = gm.dim
    return gmm.sanitize(
        GaussianMixture(
            jnp.exp(log_w).reshape(-1), means.reshape(-1, d), covs.reshape(-1, d, d), mask.reshape(-1)
        )
    )


class GSUpdate(NamedTuple):
    """What :func:`gs_update` returns: the ``K·J`` updated components and the step's diagnostics."""

    mixture: GaussianMixture
    loglik: Array  # () log p(z | past); 0 on a predict-only step
    degenerate: Array  # () every likelihood underflowed; predicted weights kept
    repaired: Array  # () a local update repaired a covariance
    missing: Array  # () the measurement held a NaN or an inf (a predict-only step)


def gs_update(local: LocalFilter, gm: GaussianMixture, z: Array, t: Any, noise: GaussianMixture) -> GSUpdate:
    """Gaussian-sum update: every component × every measurement-noise component ``j``
    (seed 000 eqs 9–16), weights normalised in the log domain; child ``i*J + j``.

    On a predict-only step (``z`` has a NaN or ``±inf`` entry) the ``J`` copies collapse to the first. If every
    likelihood underflows the predicted weights are kept and ``degenerate`` is set.
    """
    z = jnp.asarray(z)
    missing = is_missing(z)

    def one(mean, cov, rm, rP):
        new, info = local.update(local.init(mean, cov), z, t, rm, rP)
        m, P = local.moments(new)
        return m, P, info.loglik, info.repaired

    pair = jax.vmap(jax.vmap(one, (None, None, 0, 0)), (0, 0, None, None))
    means, covs, loglik, repaired = pair(gm.means, gm.covs, noise.means, noise.covs)  # (K, J, ...)
    first_only = jnp.arange(noise.capacity) == 0
    j_mask = jnp.where(missing, first_only, noise.mask)
    j_logw = jnp.where(missing, 0.0, _noise_log_weights(noise))
    # flat (K·J,) from here: XLA's CPU reductions over a trailing (K, J) pair are several times slower
    mask = (gm.mask[:, None] & j_mask[None, :]).reshape(-1)
    log_prior = (gmm.log_weights(gm)[:, None] + j_logw[None, :]).reshape(-1)
    log_prior = jnp.where(mask, log_prior, -jnp.inf)
    log_w = jnp.where(mask, log_prior + jnp.where(missing, 0.0, loglik.reshape(-1)), -jnp.inf)
    log_norm = logsumexp(log_w)
    degenerate = ~jnp.isfinite(log_norm)
    log_w = jnp.where(degenerate, log_prior, log_w)
    log_w_norm = jnp.where(degenerate, logsumexp(log_prior), log_norm)
    weights = jnp.where(mask, jnp.exp(log_w - log_w_norm), 0.0)
    d = gm.dim
    full = gmm.sanitize(GaussianMixture(weights, means.reshape(-1, d), covs.reshape(-1, d, d), mask))
    return GSUpdate(
        full, jnp.where(missing, 0.0, log_norm), degenerate, jnp.any(repaired.reshape(-1) & mask), missing
    )


def reduce_to_capacity(
    reducer: Any, gm: GaussianMixture, state: Any, capacity: int, *, key: PRNGKey | None
) -> tuple[GaussianMixture, Any, Any, Array]:
    """Call ``reducer.reduce`` and fit the result to ``capacity`` slots.

    Returns:
        ``(reduced, new_state, ReductionInfo, overflow)``.

    Raises:
        ValueError: a stateful reducer whose output capacity is not ``capacity`` (its state could
            not stay aligned with the slots).
    """
    out, new_state, info = reducer.reduce(gm, state, key=key)
    if jax.tree_util.tree_leaves(new_state) and out.capacity != capacity:
        raise ValueError(
            f"reducer: a stateful reducer must return exactly capacity={capacity} slots "
            f"(got {out.capacity}); configure its output capacity"
        )
    out, overflow = fit_capacity(out, capacity, heaviest_first=getattr(reducer, "heaviest_first", False))
    return out, new_state, info, overflow | info.overflow


def check_prior(prior: Any, capacity: int) -> GaussianMixture:
    """Validate a prior mixture against a filter capacity and fit it (normalised) to ``capacity``.

    The live count is evaluated at trace time when the prior is concrete (a filter's own prior, closed
    over by ``monte_carlo`` or a user's ``jit``), so a prior the slots cannot hold is refused there
    too instead of losing its lightest components; a traced prior (``vmap`` over priors) is not
    checked.
    """
    if not isinstance(prior, GaussianMixture):
        raise ValueError(f"prior: expected a GaussianMixture, got {type(prior).__name__}")
    n_live = concrete_n_active(prior)
    if n_live is not None and n_live > capacity:
        raise ValueError(f"prior: {n_live} live components exceed the filter capacity {capacity}")
    return fit_capacity(gmm.normalize(prior), capacity)[0]


def concrete_n_active(gm: GaussianMixture) -> int | None:
    """``gm``'s live count where it is known at trace time (a concrete mixture, also one closed over
    inside ``jit``); ``None`` for a traced one. For refusing, at the API boundary, what a capacity
    cannot hold instead of truncating it silently."""
    with jax.ensure_compile_time_eval():
        n_live = gmm.n_active(gm)
    return None if isinstance(n_live, jax.core.Tracer) else int(n_live)


def build_gsf(
    model: StateSpaceModel,
    local: LocalFilter | str = "ekf",
    reducer: Any = None,
    capacity: int = 16,
    *,
    track_ise: bool = False,
) -> Filter:
    """Build a Gaussian sum filter.

    Args:
        model: the state-space model; its GM process/measurement noises and prior are the defaults
            of ``params.model``.
        local: a :class:`LocalFilter` or the name of one (see :func:`gmjax.filters.local.local_filter_for`).
        reducer: a :class:`gmjax.reduction.Reducer` config (``params.reducer``); ``None`` keeps the
            heaviest ``capacity`` (:class:`~gmjax.reduction.PruneTop`).
        capacity: ``K``, the posterior's slots (static).
        track_ise: compute the ISE of each reduction into ``extra["ise"]``. Opt-in: with
            ``O((K L J)^2)`` Gaussian evaluations per step it costs 3–4× the filter itself on the
            jump system (``benchmarks/results/gsf_kernel.md``).

    Returns:
        A :class:`~gmjax.filters.Filter` over :class:`GSFState` with :class:`GSFParams`. Its
        ``StepInfo`` reports the moments of the updated mixture (eqs 17–18), the reducer's
        ``ReductionInfo``, and ``extra = {"n_updated": live components before reduction}`` plus
        ``"ise"``, the ISE of the reduction, with ``track_ise``.

    Raises:
        ValueError: a bad model, local filter, reducer or capacity; at ``init``, a prior with more
            live components than ``capacity``.
    """
    from gmjax.reduction import PruneTop

    check_model(model)
    if isinstance(local, str):
        local = local_filter_for(model, local)
    if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
        raise ValueError(f"capacity: must be a positive int, got {capacity!r}")
    truncate_only = check_reducer(reducer) is None  # dropping anything is then an overflow
    if truncate_only:
        reducer = PruneTop(num_out=capacity, capacity=capacity)
    n_q, n_r = model.process_noise.capacity, model.measurement_noise.capacity

    def init(
        params: GSFParams, prior: GaussianMixture | None = None, *, key: PRNGKey | None = None
    ) -> GSFState:
        del key
        fitted = check_prior(params.model.prior if prior is None else prior, capacity)
        return GSFState(fitted, params.reducer.init(capacity))

    def predict(
        params: GSFParams, state: GSFState, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> GSFState:
        del key
        noise = model.noise_at(params.model.process_noise, inputs)  # e.g. Q(dt)
        predicted = gs_predict(local, state.mixture, inputs, noise)
        return GSFState(predicted, inherit(state.reducer_state, n_q))

    def update(
        params: GSFParams, state: GSFState, z: Array, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> tuple[GSFState, StepInfo]:
        up = gs_update(local, state.mixture, z, inputs, params.model.measurement_noise)
        reduced, rstate, rinfo, overflow = reduce_to_capacity(
            params.reducer, up.mixture, inherit(state.reducer_state, n_r), capacity, key=key
        )
        if truncate_only:
            overflow = overflow | (rinfo.n_in > capacity)
        mean, cov = gmm.moments(up.mixture)
        extra = {"n_updated": gmm.n_active(up.mixture)}
        if track_ise:
            extra["ise"] = metrics.ise(up.mixture, reduced)
        info = StepInfo(
            mean=mean,
            cov=cov,
            loglik=up.loglik,
            n_components=gmm.n_active(reduced),
            flags=StepFlags(up.repaired, overflow, up.degenerate, up.missing),
            reduction=rinfo,
            extra=extra,
        )
        return GSFState(reduced, rstate), info

    return Filter(init, predict, update, GSFParams(model.params, reducer))
