"""Interacting multiple models (IMM) over any of the Gaussian local filters.

Blom & Bar-Shalom (1988), in FilterPy's ``IMMEstimator`` order. With Markov transition matrix
``p_ij = P(model j at k | model i at k-1)`` (rows sum to 1) and model probabilities ``mu_i``:

* **predict** (interaction + model-conditioned prediction):
  ``c_j = sum_i p_ij mu_i``, ``mu_{i|j} = p_ij mu_i / c_j``,
  ``x0_j = sum_i mu_{i|j} x_i``, ``P0_j = sum_i mu_{i|j} (P_i + (x_i - x0_j)(x_i - x0_j)^T)``,
  then every model ``j`` predicts from ``N(x0_j, P0_j)`` with its own ``f`` and process noise;
  the state's model probabilities become the predicted ``c``.
* **update**: every model updates with its own ``h`` and measurement noise, giving ``L_j``;
  ``mu_j = c_j L_j / sum_l c_l L_l`` and the step log-likelihood is ``log sum_j c_j L_j``.

Models are different programs, so each model's step runs as one branch of ``lax.switch`` inside a
``lax.map`` over the model index (no Python loop in the compiled step, and only the selected
branch runs). All local filters must use the same state type (e.g. all :class:`GaussianState`
filters — KF, EKF, UKF, CKF, GHKF, SGKF — or all :func:`local_sckf`) and the models must have the
same state dimension. GM noises and the GM prior are moment-matched.

:func:`build_imm_gsf` is the Gaussian-mixture variant: every model-conditioned density is a mixture
handled by a Gaussian sum filter (:mod:`gmjax.filters.gsf`) with a reducer, the mixing step keeps
the mixture of mixtures, and with no reduction it is the exact jump-Markov posterior (seed 003 §4.2).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp

from gmjax import gaussian
from gmjax import mixture as gmm
from gmjax._types import Array
from gmjax.filters import kalman, sigma
from gmjax.filters._core import Filter, LocalFilter, UpdateInfo, check_model, is_missing
from gmjax.mixture import GaussianMixture
from gmjax.models._base import StateSpaceModel

__all__ = [
    "IMMState",
    "IMMInfo",
    "build_imm",
    "imm_moments",
    "LOCAL_FILTERS",
    "IMMGSFState",
    "IMMGSFInfo",
    "build_imm_gsf",
]


class IMMState(NamedTuple):
    """``states``: the model-conditioned local states stacked on a leading ``M`` axis;
    ``log_probs``: ``(M,)`` log model probabilities (predicted after ``predict``, posterior after
    ``update``)."""

    states: object
    log_probs: Array


class IMMInfo(NamedTuple):
    """``loglik`` ``()``: ``log sum_j c_j L_j``; ``model_probs`` ``(M,)`` posterior;
    ``model_infos``: each model's :class:`UpdateInfo` stacked on ``M``; ``repaired`` ``()``: any."""

    loglik: Array
    model_probs: Array
    model_infos: UpdateInfo
    repaired: Array


LOCAL_FILTERS: dict[str, Callable[..., LocalFilter]] = {
    "ekf": lambda m, **kw: kalman.local_ekf(m.f, m.h, m.f_jacobian, m.h_jacobian),
    "kf": lambda m, **kw: kalman._linearized_filter(
        kalman._affine_parts(m.f), kalman._affine_parts(m.h)
    ),
    "ukf": lambda m, **kw: sigma.local_ukf(m.f, m.h, **kw),
    "ckf": lambda m, **kw: sigma.local_ckf(m.f, m.h),
    "ghkf": lambda m, **kw: sigma.local_ghkf(m.f, m.h, **kw),
    "sgkf": lambda m, **kw: sigma.local_sgkf(m.f, m.h, **kw),
    "sckf": lambda m, **kw: sigma.local_sckf(m.f, m.h),
}


def _log(p):
    pos = p > 0
    return jnp.where(pos, jnp.log(jnp.where(pos, p, 1.0)), -jnp.inf)


def _mix(local: LocalFilter, states, log_probs, log_P):
    """Interaction step: predicted log probabilities ``(M,)`` and the mixed states."""
    means, covs = jax.vmap(local.moments)(states)
    log_joint = log_probs[:, None] + log_P  # (i, j)
    log_c = logsumexp(log_joint, axis=0)  # (j,)
    ok = jnp.isfinite(log_c)
    w = jnp.exp(log_joint - jnp.where(ok, log_c, 0.0)[None, :])  # mu_{i|j}
    w = jnp.where(ok[None, :], w, 0.0)
    x0 = jnp.einsum("ij,id->jd", w, means)
    dev = means[:, None, :] - x0[None, :, :]  # (i, j, d)
    P0 = jnp.einsum("ij,ide->jde", w, covs) + jnp.einsum("ij,ijd,ije->jde", w, dev, dev)
    # A model with c_j = 0 keeps its own state (it carries no probability).
    x0 = jnp.where(ok[:, None], x0, means)
    P0 = jnp.where(ok[:, None, None], gaussian.symmetrize(P0), covs)
    return log_c, jax.vmap(local.init)(x0, P0)


def imm_moments(local: LocalFilter):
    """``state -> (mean, cov)`` of the IMM mixture ``sum_j mu_j N(x_j, P_j)``."""

    def moments(state: IMMState):
        means, covs = jax.vmap(local.moments)(state.states)
        M = means.shape[0]
        gm = GaussianMixture(jnp.exp(state.log_probs), means, covs, jnp.ones(M, bool))
        return gmm.moments(gm)

    return moments


def _check_imm_args(models, transition, initial_probs):
    """Eager checks shared by :func:`build_imm` and :func:`build_imm_gsf`: ``(models, P, mu0)``."""
    models = list(models)
    M = len(models)
    if M == 0:
        raise ValueError("models: need at least one model")
    dims = [check_model(m) for m in models]
    if len(set(dims)) != 1:
        raise ValueError(f"models: all models must share (state, measurement) dims, got {dims}")
    Pt = np.asarray(transition, dtype=np.float64)
    if Pt.shape != (M, M):
        raise ValueError(f"transition: expected shape ({M}, {M}), got {Pt.shape}")
    if not np.all(np.isfinite(Pt)) or np.any(Pt < 0):
        raise ValueError("transition: entries must be finite and non-negative")
    if not np.allclose(Pt.sum(axis=1), 1.0, atol=1e-8):
        raise ValueError(f"transition: rows must sum to 1, got {Pt.sum(axis=1)}")
    if initial_probs is None:
        mu0 = np.full(M, 1.0 / M)
    else:
        mu0 = np.asarray(initial_probs, dtype=np.float64)
        if mu0.shape != (M,) or np.any(mu0 < 0) or not np.isclose(mu0.sum(), 1.0):
            raise ValueError(
                f"initial_probs: expected {M} non-negative probabilities summing to 1, got {mu0}"
            )
    return models, Pt, mu0


def build_imm(
    models: Sequence[StateSpaceModel],
    transition,
    *,
    filter: str | Callable[[StateSpaceModel], LocalFilter] = "ekf",
    initial_probs=None,
    **filter_kwargs,
) -> Filter:
    """An IMM filter over ``M`` models (see the module docstring).

    Args:
        models: ``M`` state-space models with the same state and measurement dimensions.
        transition: ``(M, M)`` Markov matrix, ``transition[i, j] = P(j | i)``; rows sum to 1.
        filter: the local filter of every model: one of ``"kf"``, ``"ekf"``, ``"ukf"``,
            ``"ckf"``, ``"ghkf"``, ``"sgkf"``, ``"sckf"``, or a callable ``model -> LocalFilter``.
        initial_probs: ``(M,)`` initial model probabilities (default uniform).
        **filter_kwargs: passed to the local-filter constructor (e.g. ``alpha`` for ``"ukf"``).

    Returns:
        A :class:`Filter` over :class:`IMMState`; ``update`` returns an :class:`IMMInfo`;
        ``init(prior=None)`` starts every model from the moment-matched prior (default
        ``models[0].prior``).

    Raises:
        ValueError: an empty model list, models of different dimensions, a transition matrix
            of the wrong shape / with negative entries / rows not summing to 1, bad
            ``initial_probs``, or an unknown ``filter``.
    """
    models, Pt, mu0 = _check_imm_args(models, transition, initial_probs)
    M = len(models)
    if isinstance(filter, str):
        if filter not in LOCAL_FILTERS:
            raise ValueError(f"filter: must be one of {sorted(LOCAL_FILTERS)}, got {filter!r}")
        make = LOCAL_FILTERS[filter]
        locals_ = [make(m, **filter_kwargs) for m in models]
    elif callable(filter):
        locals_ = [filter(m) for m in models]
    else:
        raise ValueError(f"filter: expected a name or a callable, got {filter!r}")
    base = locals_[0]
    dtype = models[0].prior.means.dtype
    log_P = _log(jnp.asarray(Pt, dtype))
    log_mu0 = _log(jnp.asarray(mu0, dtype))
    q = [gmm.moments(m.process_noise) for m in models]
    r = [gmm.moments(m.measurement_noise) for m in models]
    q_means, q_covs = jnp.stack([a for a, _ in q]), jnp.stack([b for _, b in q])
    r_means, r_covs = jnp.stack([a for a, _ in r]), jnp.stack([b for _, b in r])

    pred_branches = [
        (lambda s, t, qm, qc, loc=loc: loc.predict(s, t, qm, qc)) for loc in locals_
    ]
    upd_branches = [
        (lambda s, z, t, rm, rc, loc=loc: loc.update(s, z, t, rm, rc)) for loc in locals_
    ]

    def init(prior: GaussianMixture | None = None) -> IMMState:
        prior = models[0].prior if prior is None else prior
        mean, cov = gmm.moments(prior)
        one = base.init(mean, cov)
        states = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (M,) + a.shape), one)
        return IMMState(states, log_mu0.astype(mean.dtype))

    def predict(state: IMMState, t) -> IMMState:
        log_c, mixed = _mix(base, state.states, state.log_probs, log_P)

        def one(args):
            j, s, qm, qc = args
            return jax.lax.switch(j, pred_branches, s, t, qm, qc)

        states = jax.lax.map(one, (jnp.arange(M), mixed, q_means, q_covs))
        return IMMState(states, log_c)

    def update(state: IMMState, z, t) -> tuple[IMMState, IMMInfo]:
        def one(args):
            j, s, rm, rc = args
            return jax.lax.switch(j, upd_branches, s, z, t, rm, rc)

        states, infos = jax.lax.map(one, (jnp.arange(M), state.states, r_means, r_covs))
        log_joint = state.log_probs + infos.loglik
        loglik = logsumexp(log_joint)
        ok = jnp.isfinite(loglik) & ~is_missing(jnp.asarray(z))
        # a missing measurement (or every model impossible) keeps the predicted probabilities
        log_mu = jnp.where(ok, log_joint - jnp.where(ok, loglik, 0.0), state.log_probs)
        loglik = jnp.where(is_missing(jnp.asarray(z)), jnp.zeros_like(loglik), loglik)
        info = IMMInfo(loglik, jnp.exp(log_mu), infos, jnp.any(infos.repaired))
        return IMMState(states, log_mu), info

    return Filter(init, predict, update, imm_moments(base))


# ---------------------------------------------------------------------------------------------
# IMM whose model-conditioned filters are Gaussian sum filters.


class IMMGSFState(NamedTuple):
    """State of :func:`build_imm_gsf`.

    Attributes:
        modes: the model-conditioned :class:`~gmjax.filters.gsf.GSFState` stacked on a leading
            ``M`` axis (mixtures ``(M, K, ...)`` after ``update``; ``(M, M·K·L, ...)`` after a bare
            ``predict``).
        log_probs: ``(M,)`` log model probabilities (predicted after ``predict``, posterior after
            ``update``).
    """

    modes: Any
    log_probs: Array


class IMMGSFInfo(NamedTuple):
    """Per-step report of :func:`build_imm_gsf`.

    Attributes:
        mean, cov: ``(d,)``, ``(d, d)``: moments of ``sum_j mu_j p_j(x)`` where ``p_j`` is model
            ``j``'s *updated* mixture before reduction (seed 000 eqs 17–18 over all models).
        loglik: ``()`` ``log sum_j c_j p(z_k | model j, z_{1:k-1})``.
        model_probs: ``(M,)`` posterior model probabilities ``mu_j``.
        n_components: ``()`` live components after reduction, summed over the models.
        ise: ``()`` ``sum_j mu_j ISE_j``, the model-probability-weighted ISE of the per-model
            reductions (0 unless ``track_ise``); not the ISE of the combined mixture.
        reduction: the per-model :class:`~gmjax.reduction.ReductionInfo` combined: counts summed,
            ``pruned_mass`` and ``cost`` weighted by ``mu_j``, ``labels`` concatenated,
            ``overflow`` any, and ``aux`` the per-model entries stacked on ``M``.
        overflow, repaired: ``()`` bool, any model's flag; degenerate: ``()`` bool, every model's
            likelihoods underflowed (the predicted model probabilities are kept).
        mode_infos: every model's :class:`~gmjax.filters.gsf.GSFInfo` stacked on ``M``.
    """

    mean: Array
    cov: Array
    loglik: Array
    model_probs: Array
    n_components: Array
    ise: Array
    reduction: Any
    overflow: Array
    repaired: Array
    degenerate: Array
    mode_infos: Any


def _slots_flat(tree: Any, M: int) -> Any:
    """Merge the leading ``(M, K)`` axes of every leaf into one ``M·K`` slot axis."""
    return jax.tree_util.tree_map(lambda a: a.reshape((M * a.shape[1],) + a.shape[2:]), tree)


def build_imm_gsf(
    models: Sequence[StateSpaceModel],
    transition,
    *,
    local: str | LocalFilter = "ekf",
    reducer=None,
    capacity: int = 16,
    initial_probs=None,
    track_ise: bool = False,
) -> Filter:
    """An IMM whose model-conditioned filters are Gaussian sum filters (GM prior and noises).

    This is the IMM of Blom & Bar-Shalom with every model-conditioned density a Gaussian mixture
    (the tracker of seed 003 §4.2: "IMM ... Gaussian mixture sub-filters"). With
    ``p_ij = P(model j at k | model i at k-1)``, model probabilities ``mu_i`` and model-conditioned
    mixtures ``p_i(x) = sum_k w_ik N(x; m_ik, P_ik)`` (capacity ``K`` each):

    * **interaction** (mixing): ``c_j = sum_i p_ij mu_i``, ``mu_{i|j} = p_ij mu_i / c_j`` and the
      mixed density of model ``j`` is the mixture of mixtures ``sum_i mu_{i|j} p_i(x)`` with
      ``M·K`` slots. The classical IMM collapses it to one Gaussian; here nothing is collapsed at
      mixing, so the mixed density is exact (slots with ``mu_{i|j} = 0`` are masked out). A model
      with ``c_j = 0`` keeps its own mixture.
    * **model-conditioned filtering**: model ``j``'s Gaussian sum filter
      (:func:`gmjax.filters.gsf.build_gsf`: its own ``f``, ``h``, GM process and measurement noise)
      predicts the ``M·K`` mixed components (``× L``), updates them (``× J``) and reduces the
      ``M·K·L·J`` components back to ``K`` with ``reducer`` — one reduction per model per step.
      Its measurement likelihood is ``L_j = p(z_k | model j, z_{1:k-1})`` (the GSF's ``loglik``).
    * **model probabilities**: ``mu_j = c_j L_j / sum_l c_l L_l``.

    With ``reducer=None`` and a capacity that holds every hypothesis, the result is the exact
    posterior of the jump-Markov system (a bank of Kalman filters over model sequences and noise
    components; tested). Stateful reducers (:class:`gmjax.reduction.GMRCM`) carry their per-slot
    state through mixing: the mixed slots of model ``j`` inherit the states of the slots they came
    from, so the reducer must return exactly ``capacity`` slots.

    Models are different programs, so each model's step is a branch of ``lax.switch`` inside a
    ``lax.map`` over the model index (as in :func:`build_imm`).

    Args:
        models: ``M`` state-space models with the same state and measurement dimensions.
        transition: ``(M, M)`` Markov matrix, ``transition[i, j] = P(j | i)``; rows sum to 1.
        local: the local filter of every component (a name for
            :func:`gmjax.filters.gsf.local_filter_for` or a :class:`LocalFilter` used for all models).
        reducer: any reducer of :mod:`gmjax.reduction` (``None``: keep the ``capacity`` heaviest).
        capacity: ``K``, slots of each model's posterior mixture (static).
        initial_probs: ``(M,)`` initial model probabilities (default uniform).
        track_ise: compute each model's reduction ISE (``O((M K L J)^2)`` per model and step).

    Returns:
        A :class:`Filter` over :class:`IMMGSFState`; ``init(prior=None, *, key=None)`` starts every
        model from the prior mixture (default ``models[0].prior``); ``update`` returns an
        :class:`IMMGSFInfo`; ``moments`` gives the mean and covariance of ``sum_j mu_j p_j``.

    Raises:
        ValueError: the checks of :func:`build_imm` and of :func:`gmjax.filters.gsf.build_gsf`.
    """
    from gmjax.filters.gsf import GSFState, build_gsf

    models, Pt, mu0 = _check_imm_args(models, transition, initial_probs)
    M = len(models)
    gsfs = [build_gsf(m, local, reducer, capacity, track_ise=track_ise) for m in models]
    dtype = models[0].prior.means.dtype
    log_P = _log(jnp.asarray(Pt, dtype))
    log_mu0 = _log(jnp.asarray(mu0, dtype))
    pred_branches = [(lambda s, t, g=g: g.predict(s, t)) for g in gsfs]
    upd_branches = [(lambda s, z, t, g=g: g.update(s, z, t)) for g in gsfs]

    def init(prior: GaussianMixture | None = None, *, key=None) -> IMMGSFState:
        prior = models[0].prior if prior is None else prior
        key = jax.random.key(0) if key is None else key
        one = gsfs[0].init(prior, key=key)
        modes = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (M,) + a.shape), one)
        modes = modes._replace(key=jax.random.split(key, M))
        return IMMGSFState(modes, log_mu0.astype(prior.means.dtype))

    def predict(state: IMMGSFState, t) -> IMMGSFState:
        gm = state.modes.mixture  # (M, K, ...)
        K = gm.weights.shape[1]
        log_joint = state.log_probs[:, None] + log_P  # (i, j)
        log_c = logsumexp(log_joint, axis=0)  # (j,)
        ok = jnp.isfinite(log_c)
        log_mix = log_joint - jnp.where(ok, log_c, 0.0)[None, :]  # log mu_{i|j}
        own = jnp.where(jnp.eye(M, dtype=bool), 0.0, -jnp.inf).astype(log_mix.dtype)
        log_mix = jnp.where(ok[None, :], log_mix, own)  # c_j = 0: model j keeps its own mixture
        mix = jnp.exp(log_mix)  # (i, j)
        live = mix > 0
        # mixed weights / masks of every target model j: (j, i, K) -> (j, M·K)
        w = jnp.where(live.T[:, :, None], mix.T[:, :, None] * gm.weights[None], 0.0)
        mask = live.T[:, :, None] & gm.mask[None]
        w = w.reshape(M, M * K)
        mask = mask.reshape(M, M * K)
        means = _slots_flat(gm.means, M)
        covs = _slots_flat(gm.covs, M)
        rstate = _slots_flat(state.modes.reducer_state, M)

        def one(args):
            j, wj, mj, key = args
            mixed = gmm.sanitize(GaussianMixture(wj, means, covs, mj))
            return jax.lax.switch(j, pred_branches, GSFState(mixed, key, rstate), t)

        modes = jax.lax.map(one, (jnp.arange(M), w, mask, state.modes.key))
        return IMMGSFState(modes, log_c)

    def update(state: IMMGSFState, z, t) -> tuple[IMMGSFState, IMMGSFInfo]:
        z = jnp.asarray(z)

        def one(args):
            j, s = args
            return jax.lax.switch(j, upd_branches, s, z, t)

        modes, infos = jax.lax.map(one, (jnp.arange(M), state.modes))
        missing = is_missing(z)
        log_joint = state.log_probs + infos.loglik
        loglik = logsumexp(log_joint)
        ok = jnp.isfinite(loglik) & ~missing
        log_mu = jnp.where(ok, log_joint - jnp.where(ok, loglik, 0.0), state.log_probs)
        mu = jnp.exp(log_mu)
        mean, cov = gmm.moments(GaussianMixture(mu, infos.mean, infos.cov, mu > 0))
        r = infos.reduction
        reduction = r._replace(
            n_in=jnp.sum(r.n_in),
            n_out=jnp.sum(r.n_out),
            pruned_mass=jnp.sum(mu * r.pruned_mass),
            labels=r.labels.reshape(-1),
            overflow=jnp.any(r.overflow),
            cost=jnp.sum(mu * r.cost),
        )
        info = IMMGSFInfo(
            mean=mean,
            cov=cov,
            loglik=jnp.where(missing, jnp.zeros_like(loglik), loglik),
            model_probs=mu,
            n_components=jnp.sum(infos.n_components),
            ise=jnp.sum(mu * infos.ise),
            reduction=reduction,
            overflow=jnp.any(infos.overflow),
            repaired=jnp.any(infos.repaired),
            degenerate=jnp.all(infos.degenerate),
            mode_infos=infos,
        )
        return IMMGSFState(modes, log_mu), info

    def moments(state: IMMGSFState):
        gm = state.modes.mixture
        w = jnp.exp(state.log_probs)[:, None] * gm.weights
        flat = GaussianMixture(w.reshape(-1), _slots_flat(gm.means, M), _slots_flat(gm.covs, M),
                               gm.mask.reshape(-1))
        return gmm.moments(gmm.sanitize(flat))

    return Filter(init, predict, update, moments)
