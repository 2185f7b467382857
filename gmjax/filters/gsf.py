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
survive, the ``K`` heaviest are kept, renormalised, and ``GSFInfo.overflow`` is set. With
``reducer=None`` nothing is merged: the ``K`` heaviest are kept (overflow flagged when anything is
dropped), so a capacity of at least ``K_0 (L J)^T`` gives the exact GSF over ``T`` steps.

Stateful reducers (e.g. :class:`gmjax.reduction.GMRCM`, whose low-weight rule needs per-slot
history) are recognised by their ``init_state(capacity)`` and ``step(gm, state, *, key)`` methods:
the filter carries the state aligned with the posterior's ``K`` slots, every predicted / updated
child inherits its parent's entries, and the reducer must return exactly ``K`` slots.

Time indexing follows :func:`gmjax.filters.run`: step ``k`` predicts with ``f(., t_k)`` and updates
with ``z_k`` through ``h(., t_k)``. A measurement holding a NaN is a predict-only step (the ``J``
measurement-noise copies collapse to one).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp

from gmjax import metrics
from gmjax import mixture as gmm
from gmjax._types import Array, PRNGKey
from gmjax.filters._core import Filter, LocalFilter, check_model, is_missing
from gmjax.mixture import GaussianMixture
from gmjax.models._base import StateSpaceModel
from gmjax.reduction._base import ReductionInfo, make_info

__all__ = ["GSFState", "GSFInfo", "build_gsf", "local_filter_for", "fit_capacity"]


class GSFState(NamedTuple):
    """State of a Gaussian sum filter.

    Attributes:
        mixture: the posterior (after reduction: capacity ``K``; after a bare ``predict``:
            capacity ``K·L``).
        key: PRNG key consumed by randomised reducers.
        reducer_state: a stateful reducer's per-slot state aligned with ``mixture`` (else ``None``).
    """

    mixture: GaussianMixture
    key: PRNGKey
    reducer_state: Any = None


class GSFInfo(NamedTuple):
    """Per-step report of a Gaussian sum filter update.

    Attributes:
        mean: ``(d,)`` point estimate (eq 17) of the updated mixture.
        cov: ``(d, d)`` its covariance (eq 18).
        loglik: ``()`` ``log p(z_k | z_{1:k-1})`` under the filter's mixture.
        n_updated: ``()`` live components after the update, before reduction (``<= K·L·J``).
        n_components: ``()`` live components after reduction (``<= K``).
        ise: ``()`` ISE between the updated mixture and the reduced one (seed 000 eq 42).
        reduction: the reducer's :class:`~gmjax.reduction.ReductionInfo` (``cost`` is its own
            cost, e.g. PCM's EISE).
        overflow: ``()`` bool, the reducer left more than ``K`` components (heaviest kept).
        repaired: ``()`` bool, a local filter repaired a covariance this step.
        degenerate: ``()`` bool, every component's likelihood underflowed; the weights were left
            at their predicted values (``loglik`` is then ``-inf``).
    """

    mean: Array
    cov: Array
    loglik: Array
    n_updated: Array
    n_components: Array
    ise: Array
    reduction: ReductionInfo
    overflow: Array
    repaired: Array
    degenerate: Array


Reducer = Callable[..., tuple[GaussianMixture, ReductionInfo]]


def local_filter_for(model: StateSpaceModel, name: str, **kwargs: Any) -> LocalFilter:
    """The component-level filter ``name`` (``ekf``, ``ukf``, ``ckf``, ``sckf``, ``ghkf``, ``sgkf``)
    built from the model's ``f`` and ``h``."""
    from gmjax.filters import kalman, sigma

    builders = {
        "ekf": lambda: kalman.local_ekf(model.f, model.h, model.f_jacobian, model.h_jacobian),
        "ukf": lambda: sigma.local_ukf(model.f, model.h, **kwargs),
        "ckf": lambda: sigma.local_ckf(model.f, model.h),
        "sckf": lambda: sigma.local_sckf(model.f, model.h),
        "ghkf": lambda: sigma.local_ghkf(model.f, model.h, **kwargs),
        "sgkf": lambda: sigma.local_sgkf(model.f, model.h, **kwargs),
    }
    if name not in builders:
        raise ValueError(f"local: unknown local filter {name!r}; expected one of {sorted(builders)}")
    return builders[name]()


def fit_capacity(gm: GaussianMixture, capacity: int) -> tuple[GaussianMixture, Array]:
    """Pad or truncate ``gm`` to ``capacity`` slots, keeping the heaviest; returns ``(gm, overflow)``.

    Truncation renormalises the kept weights; ``overflow`` is True when a live component was dropped.
    """
    if gm.capacity <= capacity:
        return gmm.pad(gm, capacity), jnp.zeros((), bool)
    overflow = gmm.n_active(gm) > capacity
    kept = gmm.top_k(gm, capacity)
    kept = jax.lax.cond(overflow, gmm.normalize, lambda g: g, kept)
    return kept, overflow


def _truncate(gm: GaussianMixture, *, key: PRNGKey | None = None, capacity: int) -> tuple[GaussianMixture, ReductionInfo]:
    """No reduction: keep the ``capacity`` heaviest components (labels: output slot or -1)."""
    del key
    kept, overflow = fit_capacity(gm, capacity)
    order = jnp.argsort(-jnp.where(gm.mask, gm.weights, -jnp.inf), stable=True)
    rank = jnp.zeros(gm.capacity, jnp.int32).at[order].set(jnp.arange(gm.capacity, dtype=jnp.int32))
    labels = jnp.where(gm.mask & (rank < capacity), rank, -1)
    dropped = jnp.sum(jnp.where(gm.mask & (rank >= capacity), gm.weights, 0.0))
    return kept, make_info(gm, kept, labels, pruned_mass=dropped, overflow=overflow)


def _is_stateful(reducer: Any) -> bool:
    return callable(getattr(reducer, "init_state", None)) and callable(getattr(reducer, "step", None))


def _inherit(state: Any, n_children: int) -> Any:
    """Repeat every slot's entries for its ``n_children`` children (slot ``i`` -> ``i*n .. i*n+n-1``)."""
    return jax.tree_util.tree_map(lambda a: jnp.repeat(a, n_children, axis=0), state)


def _noise_parts(noise: GaussianMixture) -> tuple[Array, Array, Array, Array]:
    """``(log weights, means, covs, mask)`` of a noise mixture (weights normalised)."""
    log_w = gmm.log_weights(noise)
    log_w = log_w - logsumexp(log_w)
    return log_w, noise.means, noise.covs, noise.mask


def build_gsf(
    model: StateSpaceModel,
    local: LocalFilter | str = "ekf",
    reducer: Reducer | None = None,
    capacity: int = 16,
    *,
    track_ise: bool = True,
) -> Filter:
    """Build a Gaussian sum filter (a :class:`~gmjax.filters.Filter`).

    Args:
        model: the state-space model; its GM process/measurement noises and prior are used as given.
        local: a :class:`LocalFilter` or the name of one (see :func:`local_filter_for`).
        reducer: any ``reducer(gm, *, key) -> (gm, ReductionInfo)`` (a
            :mod:`gmjax.reduction` config or function); ``None`` keeps the heaviest ``capacity``.
        capacity: ``K``, the posterior's slots (static).
        track_ise: compute the ISE of each reduction (``O((K L J)^2)``); off gives ``ise = 0``.

    Returns:
        ``Filter(init, predict, update, moments)``: ``init(prior=None, *, key=None)`` (the prior is
        fitted to ``capacity``; a prior with more live components than ``capacity`` is an error),
        ``predict(state, t)``, ``update(state, z, t) -> (state, GSFInfo)``, ``moments(state)``.
    """
    check_model(model)
    if isinstance(local, str):
        local = local_filter_for(model, local)
    if not isinstance(capacity, int) or capacity < 1:
        raise ValueError(f"capacity: must be a positive int, got {capacity!r}")
    q_logw, q_means, q_covs, q_mask = _noise_parts(model.process_noise)
    r_logw, r_means, r_covs, r_mask = _noise_parts(model.measurement_noise)
    stateful = _is_stateful(reducer)
    if reducer is None:
        reduce = lambda gm, state, *, key: (*_truncate(gm, key=key, capacity=capacity), None)  # noqa: E731
    elif stateful:
        def reduce(gm, state, *, key):
            out, new_state, info = reducer.step(gm, state, key=key)
            if out.capacity != capacity:
                raise ValueError(
                    f"reducer: a stateful reducer must return exactly capacity={capacity} slots "
                    f"(got {out.capacity}); configure its output capacity"
                )
            return out, info, new_state
    else:
        reduce = lambda gm, state, *, key: (*reducer(gm, key=key), None)  # noqa: E731
    n_q, n_r = model.process_noise.capacity, model.measurement_noise.capacity

    def init(prior: GaussianMixture | None = None, *, key: PRNGKey | None = None) -> GSFState:
        prior = model.prior if prior is None else prior
        if not isinstance(prior, GaussianMixture):
            raise ValueError(f"prior: expected a GaussianMixture, got {type(prior).__name__}")
        n_live = gmm.n_active(prior)
        if not isinstance(n_live, jax.core.Tracer) and int(n_live) > capacity:
            raise ValueError(f"prior: {int(n_live)} live components exceed the filter capacity {capacity}")
        fitted, _ = fit_capacity(gmm.normalize(prior), capacity)
        rstate = reducer.init_state(capacity) if stateful else None
        return GSFState(fitted, jax.random.key(0) if key is None else key, rstate)

    def predict(state: GSFState, t: Array) -> GSFState:
        gm = state.mixture

        def one(mean, cov, qm, qP):
            return local.moments(local.predict(local.init(mean, cov), t, qm, qP))

        pair = jax.vmap(jax.vmap(one, (None, None, 0, 0)), (0, 0, None, None))
        means, covs = pair(gm.means, gm.covs, q_means, q_covs)  # (K, L, d), (K, L, d, d)
        log_w = gmm.log_weights(gm)[:, None] + q_logw[None, :]
        mask = gm.mask[:, None] & q_mask[None, :]
        d = gm.dim
        flat = GaussianMixture(
            jnp.exp(log_w).reshape(-1), means.reshape(-1, d), covs.reshape(-1, d, d), mask.reshape(-1)
        )
        return GSFState(gmm.sanitize(flat), state.key, _inherit(state.reducer_state, n_q))

    def update(state: GSFState, z: Array, t: Array) -> tuple[GSFState, GSFInfo]:
        gm = state.mixture
        z = jnp.asarray(z)
        missing = is_missing(z)

        def one(mean, cov, rm, rP):
            new, info = local.update(local.init(mean, cov), z, t, rm, rP)
            m, P = local.moments(new)
            return m, P, info.loglik, info.repaired

        pair = jax.vmap(jax.vmap(one, (None, None, 0, 0)), (0, 0, None, None))
        means, covs, loglik, repaired = pair(gm.means, gm.covs, r_means, r_covs)  # (KL, J, ...)
        first_only = jnp.arange(r_mask.shape[0]) == 0
        j_mask = jnp.where(missing, first_only, r_mask)
        j_logw = jnp.where(missing, 0.0, r_logw)
        mask = gm.mask[:, None] & j_mask[None, :]
        log_prior = jnp.where(mask, gmm.log_weights(gm)[:, None] + j_logw[None, :], -jnp.inf)
        log_w = jnp.where(mask, log_prior + jnp.where(missing, 0.0, loglik), -jnp.inf)
        log_norm = logsumexp(log_w)
        # every likelihood underflowed (an extreme outlier): keep the predicted weights, flag it
        degenerate = ~jnp.isfinite(log_norm)
        log_w = jnp.where(degenerate, log_prior, log_w)
        log_w_norm = jnp.where(degenerate, logsumexp(log_prior), log_norm)
        weights = jnp.where(mask, jnp.exp(log_w - log_w_norm), 0.0)
        d = gm.dim
        full = gmm.sanitize(
            GaussianMixture(weights.reshape(-1), means.reshape(-1, d), covs.reshape(-1, d, d), mask.reshape(-1))
        )
        key, sub = jax.random.split(state.key)
        reduced, rinfo, rstate = reduce(full, _inherit(state.reducer_state, n_r), key=sub)
        reduced, overflow = fit_capacity(reduced, capacity)
        mean, cov = gmm.moments(full)
        ise = metrics.ise(full, reduced) if track_ise else jnp.zeros((), weights.dtype)
        info = GSFInfo(
            mean=mean,
            cov=cov,
            loglik=jnp.where(missing, 0.0, log_norm),
            n_updated=gmm.n_active(full),
            n_components=gmm.n_active(reduced),
            ise=ise,
            reduction=rinfo,
            overflow=overflow | rinfo.overflow,
            repaired=jnp.any(repaired & mask),
            degenerate=degenerate,
        )
        return GSFState(reduced, key, rstate), info

    def moments(state: GSFState) -> tuple[Array, Array]:
        return gmm.moments(state.mixture)

    return Filter(init, predict, update, moments)
