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
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

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

__all__ = ["IMMState", "IMMInfo", "build_imm", "imm_moments", "LOCAL_FILTERS"]


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
