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

Both builders follow the one filter contract (:class:`gmjax.filters.Filter`): the numbers — every
model's noises and prior, the transition matrix, the initial model probabilities (and, for
:func:`build_imm_gsf`, the reducer config) — live in a params pytree (:class:`IMMParams`,
:class:`IMMGSFParams`) read at every call, so ``jax.grad`` / ``jax.vmap`` with respect to them go
through :func:`gmjax.filters.run`; the log transition matrix is computed from ``params`` at each call.

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
from gmjax._types import Array, ArrayLike, PRNGKey
from gmjax.filters._core import LocalFilter, check_model, gaussian_moments, is_missing
from gmjax.filters.base import Filter, StepFlags, StepInfo, StepInputs
from gmjax.filters.local import LOCAL_FILTERS
from gmjax.mixture import GaussianMixture
from gmjax.models.base import ModelParams, StateSpaceModel

__all__ = [
    "IMMParams",
    "IMMState",
    "build_imm",
    "imm_moments",
    "LOCAL_FILTERS",
    "IMMGSFParams",
    "IMMGSFState",
    "build_imm_gsf",
]


class IMMParams(NamedTuple):
    """Parameters of :func:`build_imm` (a pytree).

    Attributes:
        models: ``M`` :class:`~gmjax.models.ModelParams`, one per model (noises as GMs or
            ``(mean, cov)`` pairs; they are moment-matched). The default prior of ``init`` is
            ``models[0].prior``.
        transition: ``(M, M)`` Markov matrix, ``transition[i, j] = P(j | i)``; rows sum to 1.
        initial_probs: ``(M,)`` initial model probabilities.
    """

    models: tuple[ModelParams, ...]
    transition: Array
    initial_probs: Array


class IMMState(NamedTuple):
    """``states``: the model-conditioned local states stacked on a leading ``M`` axis;
    ``log_probs``: ``(M,)`` log model probabilities (predicted after ``predict``, posterior after
    ``update``)."""

    states: object
    log_probs: Array


def _log(p):
    pos = p > 0
    return jnp.where(pos, jnp.log(jnp.where(pos, p, 1.0)), -jnp.inf)


def _split(key: PRNGKey | None, n: int) -> Array | None:
    """``n`` keys for the per-model calls (``None`` stays ``None``)."""
    return None if key is None else jax.random.split(key, n)


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


def imm_moments(local: LocalFilter) -> Callable[[IMMState], tuple[Array, Array]]:
    """``state -> (mean, cov)`` of the IMM mixture ``sum_j mu_j N(x_j, P_j)``."""

    def moments(state: IMMState):
        means, covs = jax.vmap(local.moments)(state.states)
        M = means.shape[0]
        gm = GaussianMixture(jnp.exp(state.log_probs), means, covs, jnp.ones(M, bool))
        return gmm.moments(gm)

    return moments


def _posterior_probs(log_probs: Array, logliks: Array, z: Array) -> tuple[Array, Array, Array]:
    """Model probabilities ``mu_j = c_j L_j / sum_l c_l L_l`` and the step log-likelihood.

    Args:
        log_probs: ``(M,)`` predicted ``log c_j``.
        logliks: ``(M,)`` ``log L_j``.
        z: ``(m,)`` the measurement (a non-finite entry: predict-only).

    Returns:
        ``(log_mu (M,), loglik (), degenerate ())``: a missing measurement, or every model
        impossible (``degenerate``), keeps the predicted probabilities; ``loglik`` is 0 on a
        predict-only step.
    """
    missing = is_missing(z)
    log_joint = log_probs + logliks
    loglik = logsumexp(log_joint)
    ok = jnp.isfinite(loglik) & ~missing
    log_mu = jnp.where(ok, log_joint - jnp.where(ok, loglik, 0.0), log_probs)
    loglik = jnp.where(missing, jnp.zeros_like(loglik), loglik)
    return log_mu, loglik, ~jnp.isfinite(loglik) & ~missing


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


def _local_filters(models, filter, filter_kwargs) -> list[LocalFilter]:
    """The local filter of every model (``filter``: a name of :data:`LOCAL_FILTERS` or a callable)."""
    if isinstance(filter, str):
        if filter not in LOCAL_FILTERS:
            raise ValueError(f"filter: must be one of {sorted(LOCAL_FILTERS)}, got {filter!r}")
        make = LOCAL_FILTERS[filter]
        return [make(m, **filter_kwargs) for m in models]
    if callable(filter):
        return [filter(m) for m in models]
    raise ValueError(f"filter: expected a name or a callable, got {filter!r}")


def build_imm(
    models: Sequence[StateSpaceModel],
    transition: ArrayLike,
    *,
    filter: str | Callable[[StateSpaceModel], LocalFilter] = "ekf",
    initial_probs: ArrayLike | None = None,
    **filter_kwargs: Any,
) -> Filter:
    """An IMM filter over ``M`` models (see the module docstring).

    Static (in the closures): ``M``, every model's ``f``/``h`` and its local filter. Numeric
    (``filter.params``, an :class:`IMMParams` read at every call): every model's noises and prior,
    the transition matrix and the initial probabilities (``log`` of both taken at call time).

    Args:
        models: ``M`` state-space models with the same state and measurement dimensions.
        transition: ``(M, M)`` Markov matrix, ``transition[i, j] = P(j | i)``; rows sum to 1.
        filter: the local filter of every model: one of ``"kf"``, ``"ekf"``, ``"ukf"``,
            ``"ckf"``, ``"ghkf"``, ``"sgkf"``, ``"sckf"``, or a callable ``model -> LocalFilter``.
        initial_probs: ``(M,)`` initial model probabilities (default uniform).
        **filter_kwargs: passed to the local-filter constructor (e.g. ``alpha`` for ``"ukf"``).

    Returns:
        A :class:`Filter` over :class:`IMMState` with :class:`IMMParams`; the key is unused
        (``None`` is fine). ``init(params, prior=None)`` starts every model from the
        moment-matched prior (default ``params.models[0].prior``). ``update``'s
        :class:`StepInfo` reports the moments of ``sum_j mu_j N(x_j, P_j)`` after the update,
        ``loglik = log sum_j c_j L_j``, ``n_components = M`` (the posterior is an ``M``-component
        mixture), ``flags.repaired`` (any model), ``flags.degenerate`` (every model's likelihood
        underflowed: predicted probabilities kept), ``reduction=None`` and ``extra`` =
        ``{"model_probs": (M,) posterior mu_j, "model_loglik": (M,) log L_j,
        "innovation": (M, m), "innovation_cov": (M, m, m)}``.

    Raises:
        ValueError: an empty model list, models of different dimensions, a transition matrix
            of the wrong shape / with negative entries / rows not summing to 1, bad
            ``initial_probs``, or an unknown ``filter``.
    """
    models, Pt, mu0 = _check_imm_args(models, transition, initial_probs)
    M = len(models)
    locals_ = _local_filters(models, filter, filter_kwargs)
    base = locals_[0]
    dtype = models[0].prior.means.dtype
    params0 = IMMParams(tuple(m.params for m in models), jnp.asarray(Pt, dtype), jnp.asarray(mu0, dtype))
    moments = imm_moments(base)

    def pred_branch(j: int) -> Callable:
        def predict_j(p, s, t):
            x = locals_[j].moments(s)[0] if models[j].state_dependent_noise else None  # mixed mean
            noise = models[j].noise_at(p.models[j].process_noise, t, x)
            return locals_[j].predict(s, t, *gaussian_moments(noise))

        return predict_j

    def upd_branch(j: int) -> Callable:
        return lambda p, s, z, t: locals_[j].update(s, z, t, *gaussian_moments(p.models[j].measurement_noise))

    pred_branches = [pred_branch(j) for j in range(M)]
    upd_branches = [upd_branch(j) for j in range(M)]

    def init(params: IMMParams, prior: Any = None, *, key: PRNGKey | None = None) -> IMMState:
        del key
        mean, cov = gaussian_moments(params.models[0].prior if prior is None else prior)
        one = base.init(mean, cov)
        states = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (M,) + a.shape), one)
        return IMMState(states, _log(params.initial_probs).astype(mean.dtype))

    def predict(
        params: IMMParams, state: IMMState, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> IMMState:
        del key
        log_c, mixed = _mix(base, state.states, state.log_probs, _log(params.transition))

        def one(args):
            j, s = args
            return jax.lax.switch(j, pred_branches, params, s, inputs)

        return IMMState(jax.lax.map(one, (jnp.arange(M), mixed)), log_c)

    def update(
        params: IMMParams, state: IMMState, z: Array, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> tuple[IMMState, StepInfo]:
        del key
        z = jnp.asarray(z)

        def one(args):
            j, s = args
            return jax.lax.switch(j, upd_branches, params, s, z, inputs)

        states, infos = jax.lax.map(one, (jnp.arange(M), state.states))
        log_mu, loglik, degenerate = _posterior_probs(state.log_probs, infos.loglik, z)
        new = IMMState(states, log_mu)
        mean, cov = moments(new)
        flags = StepFlags(jnp.any(infos.repaired), jnp.zeros((), bool), degenerate, is_missing(z))
        extra = {
            "model_probs": jnp.exp(log_mu),
            "model_loglik": infos.loglik,
            "innovation": infos.innovation,
            "innovation_cov": infos.innovation_cov,
        }
        return new, StepInfo(mean, cov, loglik, jnp.asarray(M, jnp.int32), flags, None, extra)

    return Filter(init, predict, update, params0)


# ---------------------------------------------------------------------------------------------
# IMM whose model-conditioned filters are Gaussian sum filters.


class IMMGSFParams(NamedTuple):
    """Parameters of :func:`build_imm_gsf` (a pytree).

    Attributes:
        models: ``M`` :class:`~gmjax.models.ModelParams` (GM prior and noises), one per model; the
            default prior of ``init`` is ``models[0].prior``.
        reducer: ONE reducer config shared by every model's Gaussian sum filter (its thresholds are
            leaves: differentiate or tune them here).
        transition: ``(M, M)`` Markov matrix, ``transition[i, j] = P(j | i)``; rows sum to 1.
        initial_probs: ``(M,)`` initial model probabilities.
    """

    models: tuple[ModelParams, ...]
    reducer: Any
    transition: Array
    initial_probs: Array


class IMMGSFState(NamedTuple):
    """State of :func:`build_imm_gsf`.

    Attributes:
        modes: the model-conditioned :class:`~gmjax.filters.gsf.GSFState` stacked on a leading
            ``M`` axis (mixtures ``(M, K, ...)`` after ``update``; ``(M, M·K·L, ...)`` after a bare
            ``predict``; the reducer states aligned with those slots).
        log_probs: ``(M,)`` log model probabilities (predicted after ``predict``, posterior after
            ``update``).
    """

    modes: Any
    log_probs: Array


def _slots_flat(tree: Any, M: int) -> Any:
    """Merge the leading ``(M, K)`` axes of every leaf into one ``M·K`` slot axis."""
    return jax.tree_util.tree_map(lambda a: a.reshape((M * a.shape[1],) + a.shape[2:]), tree)


def _mix_mixtures(gm: GaussianMixture, log_probs: Array, log_P: Array) -> tuple[Array, Array, Array]:
    """Interaction of model-conditioned mixtures, nothing collapsed.

    Args:
        gm: the ``M`` posterior mixtures stacked on ``M`` (weights ``(M, K)``).
        log_probs: ``(M,)`` posterior ``log mu_i``.
        log_P: ``(M, M)`` ``log p_ij``.

    Returns:
        ``(log_c (M,), weights (M, M·K), mask (M, M·K))``: row ``j`` weights slot ``(i, k)`` by
        ``mu_{i|j} w_ik``; slots with ``mu_{i|j} = 0`` are masked out; a model with ``c_j = 0``
        keeps its own mixture.
    """
    M, K = gm.weights.shape
    log_joint = log_probs[:, None] + log_P  # (i, j)
    log_c = logsumexp(log_joint, axis=0)  # (j,)
    ok = jnp.isfinite(log_c)
    log_mix = log_joint - jnp.where(ok, log_c, 0.0)[None, :]  # log mu_{i|j}
    own = jnp.where(jnp.eye(M, dtype=bool), 0.0, -jnp.inf).astype(log_mix.dtype)
    log_mix = jnp.where(ok[None, :], log_mix, own)
    mix = jnp.exp(log_mix)  # (i, j)
    live = mix > 0
    w = jnp.where(live.T[:, :, None], mix.T[:, :, None] * gm.weights[None], 0.0)  # (j, i, K)
    mask = live.T[:, :, None] & gm.mask[None]
    return log_c, w.reshape(M, M * K), mask.reshape(M, M * K)


def _combine_reduction(r: Any, mu: Array) -> Any:
    """The per-model :class:`~gmjax.reduction.ReductionInfo` (stacked on ``M``) as one: counts
    summed, ``pruned_mass`` and ``cost`` weighted by ``mu_j``, ``labels`` concatenated,
    ``overflow`` and ``invalid_threshold`` any, ``aux`` kept stacked on ``M``."""
    return r._replace(
        n_in=jnp.sum(r.n_in),
        n_out=jnp.sum(r.n_out),
        pruned_mass=jnp.sum(mu * r.pruned_mass),
        labels=r.labels.reshape(-1),
        overflow=jnp.any(r.overflow),
        cost=jnp.sum(mu * r.cost),
        invalid_threshold=jnp.any(r.invalid_threshold),
    )


def _imm_gsf_info(log_mu: Array, loglik: Array, infos: StepInfo) -> StepInfo:
    """The IMM-GSF :class:`StepInfo` from the models' GSF infos (stacked on ``M``) and the
    posterior model probabilities (see :func:`build_imm_gsf`)."""
    mu = jnp.exp(log_mu)
    mean, cov = gmm.moments(GaussianMixture(mu, infos.mean, infos.cov, mu > 0))
    flags = StepFlags(
        repaired=jnp.any(infos.flags.repaired),
        overflow=jnp.any(infos.flags.overflow),
        degenerate=jnp.all(infos.flags.degenerate),
        nonfinite_measurement=jnp.any(infos.flags.nonfinite_measurement),
    )
    extra = {
        "model_probs": mu,
        "model_loglik": infos.loglik,
        "mode_mean": infos.mean,
        "mode_cov": infos.cov,
        "mode_n_components": infos.n_components,
        "n_updated": jnp.sum(infos.extra["n_updated"]),
        "mode_reduction": infos.reduction,
    }
    if "ise" in infos.extra:
        extra["ise"] = jnp.sum(mu * infos.extra["ise"])
    return StepInfo(
        mean,
        cov,
        loglik,
        jnp.sum(infos.n_components).astype(jnp.int32),
        flags,
        _combine_reduction(infos.reduction, mu),
        extra,
    )


def build_imm_gsf(
    models: Sequence[StateSpaceModel],
    transition: ArrayLike,
    *,
    local: str | LocalFilter = "ekf",
    reducer: Any = None,
    capacity: int = 16,
    initial_probs: ArrayLike | None = None,
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
      (:func:`gmjax.filters.gsf.build_gsf`: its own ``f``, ``h``, GM process and measurement noise,
      called with ``GSFParams(params.models[j], params.reducer)``) predicts the ``M·K`` mixed
      components (``× L``, seed 000 eqs 4–8), updates them (``× J``, eqs 9–16) and reduces the
      ``M·K·L·J`` components back to ``K`` with the reducer — one reduction per model per step.
      Its measurement likelihood is ``L_j = p(z_k | model j, z_{1:k-1})`` (the GSF's ``loglik``).
    * **model probabilities**: ``mu_j = c_j L_j / sum_l c_l L_l``.

    With ``reducer=None`` and a capacity that holds every hypothesis, the result is the exact
    posterior of the jump-Markov system (a bank of Kalman filters over model sequences and noise
    components; tested). Stateful reducers (:class:`gmjax.reduction.GMRCM`) carry their per-slot
    state through mixing: the mixed slots of model ``j`` inherit the states of the slots they came
    from, so the reducer must return exactly ``capacity`` slots.

    Static (in the closures): ``M``, ``capacity``, every model's ``f``/``h`` and local filter, the
    noise component counts ``L``, ``J`` (shapes), ``track_ise``. Numeric (``filter.params``, an
    :class:`IMMGSFParams` read at every call): every model's GM noises and prior, ONE reducer
    config shared by all models, the transition matrix and the initial probabilities. The key,
    when given, is split over the ``M`` model filters at every call (the reducers of
    :mod:`gmjax.reduction` draw nothing, so ``None`` is fine).

    Args:
        models: ``M`` state-space models with the same state and measurement dimensions and the
            same numbers of process- and measurement-noise components.
        transition: ``(M, M)`` Markov matrix, ``transition[i, j] = P(j | i)``; rows sum to 1.
        local: the local filter of every component (a name for
            :func:`gmjax.filters.local.local_filter_for` or a :class:`LocalFilter` used for all models).
        reducer: any reducer of :mod:`gmjax.reduction`, shared by the models (``None``:
            :class:`~gmjax.reduction.PruneTop` keeping the ``capacity`` heaviest).
        capacity: ``K``, slots of each model's posterior mixture (static).
        initial_probs: ``(M,)`` initial model probabilities (default uniform).
        track_ise: compute each model's reduction ISE (``O((M K L J)^2)`` per model and step).

    Returns:
        A :class:`Filter` over :class:`IMMGSFState` with :class:`IMMGSFParams`;
        ``init(params, prior=None)`` starts every model from the prior mixture (default
        ``params.models[0].prior``). ``update``'s :class:`StepInfo`: ``mean``, ``cov`` = moments
        of ``sum_j mu_j p_j(x)`` over every model's *updated* mixture before reduction (seed 000
        eqs 17–18 over all models); ``loglik = log sum_j c_j L_j``; ``n_components`` = live
        components after reduction summed over the models; ``flags``: ``repaired`` / ``overflow``
        any model's, ``degenerate`` every model's likelihoods underflowed (predicted model
        probabilities kept); ``reduction`` = the per-model ``ReductionInfo`` combined into one
        (counts summed, ``pruned_mass`` and ``cost`` weighted by ``mu_j``, ``labels``
        concatenated, ``overflow`` any, ``aux`` stacked on ``M``), so the consumers that read
        ``reduction.cost`` per step (Monte Carlo AEISE) get the model-probability-weighted cost;
        ``extra`` = ``{"model_probs": (M,) mu_j, "model_loglik": (M,) log L_j, "mode_mean":
        (M, d), "mode_cov": (M, d, d) each model's pre-reduction moments, "mode_n_components":
        (M,), "n_updated": () live components before reduction (all models), "mode_reduction":
        the per-model ReductionInfo stacked on M}``, and with ``track_ise`` ``"ise"``: ()
        ``sum_j mu_j ISE_j`` (not the ISE of the combined mixture).

    Raises:
        ValueError: the checks of :func:`build_imm` and of :func:`gmjax.filters.gsf.build_gsf`;
            models with different numbers of noise components.
    """
    from gmjax.filters.gsf import GSFParams, GSFState, build_gsf, check_reducer
    from gmjax.reduction import PruneTop

    models, Pt, mu0 = _check_imm_args(models, transition, initial_probs)
    M = len(models)
    counts = {(m.process_noise.capacity, m.measurement_noise.capacity) for m in models}
    if len(counts) != 1:
        raise ValueError(
            f"models: all models must have the same numbers of (process, measurement) "
            f"noise components, got {sorted(counts)}"
        )
    gsfs = [build_gsf(m, local, reducer, capacity, track_ise=track_ise) for m in models]
    reducer = PruneTop(num_out=capacity) if check_reducer(reducer) is None else reducer
    dtype = models[0].prior.means.dtype
    params0 = IMMGSFParams(
        tuple(m.params for m in models), reducer, jnp.asarray(Pt, dtype), jnp.asarray(mu0, dtype)
    )

    def pred_branch(j: int) -> Callable:
        g = gsfs[j]
        return lambda p, s, inp, k: g.predict(GSFParams(p.models[j], p.reducer), s, inp, key=k)

    def upd_branch(j: int) -> Callable:
        g = gsfs[j]
        return lambda p, s, z, inp, k: g.update(GSFParams(p.models[j], p.reducer), s, z, inp, key=k)

    pred_branches = [pred_branch(j) for j in range(M)]
    upd_branches = [upd_branch(j) for j in range(M)]

    def init(
        params: IMMGSFParams, prior: GaussianMixture | None = None, *, key: PRNGKey | None = None
    ) -> IMMGSFState:
        prior = params.models[0].prior if prior is None else prior
        one = gsfs[0].init(GSFParams(params.models[0], params.reducer), prior, key=key)
        modes = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (M,) + a.shape), one)
        return IMMGSFState(modes, _log(params.initial_probs).astype(prior.means.dtype))

    def predict(
        params: IMMGSFParams, state: IMMGSFState, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> IMMGSFState:
        gm = state.modes.mixture  # (M, K, ...)
        log_c, w, mask = _mix_mixtures(gm, state.log_probs, _log(params.transition))
        means, covs = _slots_flat(gm.means, M), _slots_flat(gm.covs, M)
        rstate = _slots_flat(state.modes.reducer_state, M)

        def one(args):
            j, wj, mj, kj = args
            mixed = GSFState(gmm.sanitize(GaussianMixture(wj, means, covs, mj)), rstate)
            return jax.lax.switch(j, pred_branches, params, mixed, inputs, kj)

        modes = jax.lax.map(one, (jnp.arange(M), w, mask, _split(key, M)))
        return IMMGSFState(modes, log_c)

    def update(
        params: IMMGSFParams, state: IMMGSFState, z: Array, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> tuple[IMMGSFState, StepInfo]:
        z = jnp.asarray(z)

        def one(args):
            j, s, kj = args
            return jax.lax.switch(j, upd_branches, params, s, z, inputs, kj)

        modes, infos = jax.lax.map(one, (jnp.arange(M), state.modes, _split(key, M)))
        log_mu, loglik, _ = _posterior_probs(state.log_probs, infos.loglik, z)
        return IMMGSFState(modes, log_mu), _imm_gsf_info(log_mu, loglik, infos)

    return Filter(init, predict, update, params0)
