"""Linear Gaussian sum filters (banks of Kalman filters) with the reductions of seed 004 (Pishdad & Labeau 2014).

Pishdad & Labeau, *A New Reduction Scheme for Gaussian Sum Filters*. The model is linear (affine)
``x_k = F x_{k-1} + v_k``, ``z_k = H x_k + w_k`` (eqs 1–2) with GM process noise
``sum_i w^i N(u^i, Q^i)`` (eq 3, ``L`` clusters) and GM measurement noise ``sum_j p^j N(b^j, R^j)``
(eq 4, ``J`` clusters). As in the paper (§III, first paragraph) the posterior is a single Gaussian
at the end of every step: from ``N(x̂_{k-1}, P_{k-1})`` the bank runs one Kalman filter per model
``M^{ij}`` (eqs 5–8) with weights ``mu^{ij}`` (eq 9) and one reduction keeps one Gaussian:

================  ==========================================================================
``method``        reduction
================  ==========================================================================
``gsf-merge``     moment-matched merge of all ``L·J`` clusters (eqs 10–11)
``gsf-remove``    keep the cluster of largest ``mu^{ij}`` (eqs 12–14)
``matched``       keep the *true* active cluster (oracle; reads ``inputs.aux``, see below)
``kf-mm``         a Kalman filter on the moment-matched noises (``L = J = 1``)
``red-gsfm``      active-cluster reduction (eqs 15–17), initial estimate = GSF-merge mean (eq 10)
``red-gsfr``      … initial estimate = GSF-remove mean (eqs 12–13)
``red-pkg``       … initial estimate = GSF-merge mean with preloaded Kalman gains (§IV-A 3)
``red-ssg``       … initial estimate = GSF-merge mean with each sub-filter's steady-state gain (§IV-A 4)
``red-dkg``       … initial estimate = one Kalman-filter step on the moment-matched noises (§IV-A 5)
================  ==========================================================================

The active-cluster reduction: with an initial estimate ``x̌_k`` the noises are approximated by
``v̌_k = x̌_k - F x̂_{k-1}`` (eq 15) and ``w̌_k = z_k - H x̌_k`` (eq 16), the model
``M* = argmax_ij w^i N(v̌; u^i, Q^i) p^j N(w̌; b^j, R^j)`` (eq 17) is chosen, and the posterior is
that model's Kalman posterior ``(x̂^{ij}_{k|k}, P^{ij}_{k|k})`` computed from ``(x̂_{k-1}, P_{k-1})``
(the other clusters are removed). Because eq 17 factorises, ``i*`` and ``j*`` are two argmaxes.

The bank is the Gaussian sum filter of one Gaussian: the prediction is
:func:`gmjax.filters.gsf.gs_predict` of ``N(x̂_{k-1}, P_{k-1})`` with the ``L`` process clusters
(eqs 5–6) and the full bank is :func:`gmjax.filters.gsf.gs_update` of that ``L``-component mixture
with the ``J`` measurement clusters (eqs 7–9; child ``i J + j`` is model ``M^{ij}``).

Readings where the paper is not explicit (each also stated where it is implemented):

* **Rank-deficient process noise.** In the random-walk-velocity model (eqs 20–22) ``v_k = G v``
  with scalar ``v`` and ``G = (dt, 1)^T``, so ``Q^i`` is rank one and ``N(v̌; u^i, Q^i)`` in eq 17
  is singular. With ``noise_gain=G`` the process-noise term of eq 17 is evaluated for the scalar
  ``G^+ v̌`` against ``N(G^+ u^i, G^+ Q^i G^{+T})`` (``G^+`` the pseudo-inverse); the default
  ``noise_gain="auto"`` finds ``G`` from the eigenvectors of ``sum_i w^i Q^i`` whose eigenvalues
  exceed ``1e-6`` of the largest (identity, i.e. the full density, when ``Q`` is full rank).
  ``G^+`` is a static, build-time quantity (``"auto"`` needs concrete arrays); the cluster
  means and covariances it projects are read from ``params`` at every call.
* **Red-PKG** (§IV-A 3): "GSF-merge state estimation, but with preloaded Kalman gains" that "can
  be evaluated offline". We take the gain sequence ``K̄_k`` of the Riccati recursion with the
  weight-averaged cluster covariances ``Q̄ = sum_i w^i Q^i``, ``R̄ = sum_j p^j R^j`` from the prior
  covariance. It does not depend on the data (so it is the offline table; we carry its covariance
  ``P̄`` in the state instead of indexing a precomputed table). Every sub-filter uses ``K̄_k`` and
  ``S̄_k`` (also in its weight, eq 9). This is the reading under which the paper's remark of §V-A
  holds: with equal cluster variances "the preloaded Kalman gains and the gains of individual
  filters will be the same … Red-GSFM and Red-PKG will provide the same results" (tested). The
  other reading (the moment-matched Kalman filter's gain) would make that remark false.
* **Red-SSG** (§IV-A 4): sub-filter ``(i, j)`` uses its steady-state gain and innovation
  covariance, the fixed point of the Riccati recursion with ``(F, H, Q^i, R^j)`` (``F`` and ``H``
  at ``t = 1``; the model must be time invariant), found by ``ssg_iterations`` Riccati steps
  from the covariance of ``params.model.prior`` (checked against ``scipy.linalg.solve_discrete_are``
  in the tests). They are computed from ``params`` in ``init`` and carried in the state
  (:attr:`BankState.ss_gain`, :attr:`BankState.ss_innovation_cov`), so ``jax.grad`` w.r.t. the
  noise covariances reaches them and a step does not repeat the 2000 iterations.
* **Red-DKG** (§IV-A 5): "the gain of a Kalman filter run at that iteration", computed from this
  filter's own ``P_{k-1}``; the Kalman filter of the paper's comparisons is the one on the
  moment-matched noises, so ``x̌_k`` is one such Kalman step from ``(x̂_{k-1}, P_{k-1})``. This
  matches §V-A: Red-DKG suffers where "a single Gaussian distribution cannot represent" the noise.
* **Matched** (§III-A): it keeps the cluster of the model that generated the data. The true
  ``(i, j)`` is passed per step in ``inputs.aux`` (``(2,)`` int): run it with
  ``gmjax.filters.run(filt, zs, StepInputs(t=ts, aux=active))``, ``active`` ``(T, 2)`` from
  :func:`gmjax.scenarios.uwb_velocity.simulate_labeled`. Without it the matched filter raises
  ``ValueError``.
* **Log-likelihood** (``StepInfo.loglik``): the log of the normaliser of eq 9 for the bank's own
  Kalman sub-filters, ``log sum_ij w^i p^j N(z_k; ẑ^{ij}, S^{ij})`` from ``(x̂_{k-1}, P_{k-1})``,
  i.e. ``log p(z_k | z_{1:k-1})`` under the filter's predicted Gaussian sum, for every method
  (``kf-mm``: its single moment-matched model). It is not the normaliser of the approximate-gain
  weights of Red-PKG / Red-SSG. Methods that do not use the full bank still compute it; under
  ``jit`` XLA drops that work when ``loglik`` is not used.
* **Missing measurement** (a NaN in ``z``): every method returns the moment-matched prediction
  (log-likelihood 0).
* **Per-step inputs.** ``f`` and ``h`` receive the step's :class:`~gmjax.filters.StepInputs` in
  the model's call convention (``f(x, t)``, ``f(x, u, t)`` with a control, ``f(x, inputs)``), so
  irregular ``dt`` and controls reach ``F x + B u``; ``F`` and ``H`` are the Jacobians at each step.
  The process clusters of every step are ``model.noise_at(params.model.process_noise, inputs)``
  (``Q(dt)``; as :func:`~gmjax.filters.gsf.build_gsf` reads them), in eqs 5–6, in eq 17, in
  ``Q̄`` (Red-PKG) and in the moment-matched noise (``kf-mm``, Red-DKG). With ``noise_gain="auto"``
  and a per-step process noise whose clusters are rank deficient, ``G^+`` of eq 17 is re-derived
  at every step from the leading eigenvectors of that step's ``sum_i w^i Q^i(dt)`` (the rank is
  fixed at build time), so a noise direction that moves with ``dt`` (``G = (dt, 1)^T``) is
  followed; an explicit ``noise_gain`` stays fixed. Red-SSG's steady-state gains are computed
  once, from ``F``, ``H`` at ``StepInputs(t=1, dt=1)`` (no control) and the noises in ``params``:
  a steady state only exists for a time-invariant model. The bank ignores ``angle_dims``
  (a linear model).

Time indexing follows :func:`gmjax.filters.run`.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax import mixture as gmm
from gmjax._types import Array, PRNGKey
from gmjax.filters._bank_reduction import Linearize as Linearize
from gmjax.filters._bank_reduction import (
    _argmax2,
    _average_cov,
    _bank_noises,
    _gain_estimate,
    _matched_pair,
    _merge,
    _noise_log_weights,
    _one_update,
    _preload_update,
    _resolve_noise_gain,
    _select,
    _Static,
    _step_gain,
)
from gmjax.filters._core import check_model, is_missing, kalman_gain, repair_cov, safe_chol
from gmjax.filters._linearized import affine_parts, linearized_filter
from gmjax.filters.base import Filter, StepFlags, StepInfo, StepInputs, run
from gmjax.filters.gsf import gs_predict, gs_update
from gmjax.mixture import GaussianMixture
from gmjax.models.base import ModelParams, StateSpaceModel

__all__ = [
    "BANK_METHODS",
    "BankParams",
    "BankState",
    "build_bank",
    "sweep_errors",
    "steady_state_gains",
]

BANK_METHODS = (
    "gsf-merge",
    "gsf-remove",
    "matched",
    "kf-mm",
    "red-gsfm",
    "red-gsfr",
    "red-pkg",
    "red-ssg",
    "red-dkg",
)
_FULL_BANK = ("gsf-merge", "gsf-remove", "red-gsfm", "red-gsfr")


class BankParams(NamedTuple):
    """Parameters of :func:`build_bank` (a pytree).

    Attributes:
        model: the model's prior and its GM process / measurement noises (the ``L`` and ``J``
            clusters of eqs 3–4). Everything derived from them — the normalised log weights, the
            moment-matched noises (``kf-mm``, ``red-dkg``), ``Q̄``/``R̄`` (``red-pkg``) and the
            steady-state gains (``red-ssg``, in ``init``) — is computed from here at call time.
    """

    model: ModelParams


class BankState(NamedTuple):
    """State of a linear GSF bank.

    Attributes:
        mean: ``(d,)`` after ``update`` the posterior ``x̂_{k|k}``; after ``predict`` the mean of the
            predicted mixture.
        cov: ``(d, d)`` the matching covariance.
        predicted: the predicted mixture of ``L`` slots, ``N(F x̂_{k-1} + u^i, F P_{k-1} F^T + Q^i)``
            with weights ``w^i`` (eqs 5–6; after ``init``: the prior on every slot).
        f_mean: ``(d,)`` ``F x̂_{k-1}`` (the reference point of eq 15).
        f_cov: ``(d, d)`` ``F P_{k-1} F^T`` (Red-DKG adds the moment-matched ``Q`` to it).
        preload_cov: ``(d, d)`` the data-independent covariance of the preloaded-gain recursion
            (Red-PKG; posterior after ``update``, prediction after ``predict``).
        ss_gain: ``(L, J, d, m)`` the steady-state gains of ``red-ssg`` (computed in ``init``);
            ``None`` for the other methods.
        ss_innovation_cov: ``(L, J, m, m)`` the matching innovation covariances, or ``None``.
    """

    mean: Array
    cov: Array
    predicted: GaussianMixture
    f_mean: Array
    f_cov: Array
    preload_cov: Array
    ss_gain: Array | None = None
    ss_innovation_cov: Array | None = None


# ---------------------------------------------------------------------------------------------
# Quantities derived from the parameters (computed at call time).


def _riccati_step(P: Array, F: Array, H: Array, Q: Array, R: Array) -> tuple[Array, Array, Array]:
    """One predict + update of the covariance: ``(P_post, K, S)`` from the previous posterior ``P``."""
    Pp = gaussian.symmetrize(F @ P @ F.T + Q)
    S = gaussian.symmetrize(H @ Pp @ H.T + R)
    K = kalman_gain(Pp @ H.T, safe_chol(S).factor)
    A = jnp.eye(P.shape[0], dtype=P.dtype) - K @ H
    return gaussian.symmetrize(A @ Pp @ A.T + K @ R @ K.T), K, S


def steady_state_gains(
    F: Array, H: Array, Q: Array, R: Array, P0: Array, *, iterations: int = 2000
) -> tuple[Array, Array]:
    """Steady-state Kalman gain and innovation covariance of ``(F, H, Q, R)`` (traceable).

    Iterates the Riccati recursion ``iterations`` times from ``P0`` (a ``lax.fori_loop``).

    Returns:
        ``(K (d, m), S (m, m))``.
    """
    P = jax.lax.fori_loop(0, iterations, lambda _, P: _riccati_step(P, F, H, Q, R)[0], P0)
    _, K, S = _riccati_step(P, F, H, Q, R)
    return K, S


def _pair_steady_state_gains(
    q_covs: Array, r_covs: Array, F: Array, H: Array, P0: Array, iterations: int
) -> tuple[Array, Array]:
    """:func:`steady_state_gains` of every model ``(i, j)``: ``(L, J, d, m)``, ``(L, J, m, m)``."""
    one = lambda Q, R: steady_state_gains(F, H, Q, R, P0, iterations=iterations)  # noqa: E731
    return jax.vmap(jax.vmap(one, (None, 0)), (0, None))(q_covs, r_covs)


# ---------------------------------------------------------------------------------------------
# One step of a bank (module-level pure functions; ``cfg`` holds the static part).


def _init(cfg: _Static, params: BankParams, prior: GaussianMixture | None) -> BankState:
    """The moment-matched prior and, for ``red-ssg``, the steady-state gains from ``params``."""
    prior = params.model.prior if prior is None else prior
    if not isinstance(prior, GaussianMixture):
        raise ValueError(f"prior: expected a GaussianMixture, got {type(prior).__name__}")
    d, dtype = cfg.dim, params.model.prior.means.dtype
    mean, cov = (a.astype(dtype) for a in gmm.moments(prior))
    q_noise, r_noise = _bank_noises(params.model, cfg.method)
    n_q = q_noise.capacity
    predicted = gmm.sanitize(
        GaussianMixture(
            jnp.exp(_noise_log_weights(q_noise)),
            jnp.broadcast_to(mean, (n_q, d)),
            jnp.broadcast_to(cov, (n_q, d, d)),
            q_noise.mask,
        )
    )
    ss_gain = ss_cov = None
    if cfg.method == "red-ssg":  # F and H at t = 1, dt = 1: the model must be time invariant
        t1 = StepInputs(t=jnp.ones((), jnp.int32), dt=jnp.ones((), dtype))
        try:
            F1 = cfg.f_lin(jnp.zeros((d,), dtype), t1)[1]
            H1 = cfg.h_lin(jnp.zeros((d,), dtype), t1)[1]
        except Exception as e:  # e.g. f(x, u, t) that cannot take u = None
            raise ValueError(
                "method: 'red-ssg' evaluates F and H once, at StepInputs(t=1, dt=1) without a "
                f"control, for its steady-state gains; the model's f or h failed there ({e!r})"
            ) from e
        ss_gain, ss_cov = _pair_steady_state_gains(
            q_noise.covs, r_noise.covs, F1, H1, gmm.cov(params.model.prior), cfg.ssg_iterations
        )
    return BankState(mean, cov, predicted, mean, cov, cov, ss_gain, ss_cov)


def _predict(cfg: _Static, params: BankParams, state: BankState, inputs: Any) -> BankState:
    """Eqs 5–6 for every process cluster (the step's process noise, e.g. ``Q(dt)``), and the
    preloaded-gain covariance prediction."""
    q_noise, _ = _bank_noises(params.model, cfg.method, cfg.noise_at, inputs)
    fm, F = cfg.f_lin(state.mean, inputs)
    predicted = gs_predict(cfg.local, gmm.from_gaussian(state.mean, state.cov), inputs, q_noise)
    mean, cov = gmm.moments(predicted)
    preload = gaussian.symmetrize(F @ state.preload_cov @ F.T + _average_cov(q_noise))
    f_cov = gaussian.symmetrize(F @ state.cov @ F.T)
    return state._replace(
        mean=mean, cov=cov, predicted=predicted, f_mean=fm, f_cov=f_cov, preload_cov=preload
    )


def _reduce_full(
    cfg: _Static,
    q_noise: GaussianMixture,
    r_noise: GaussianMixture,
    state: BankState,
    up: Any,
    z: Array,
    inputs: Any,
) -> tuple[Array, Array, Array, Array]:
    """``gsf-merge``, ``gsf-remove``, ``red-gsfm``, ``red-gsfr``: reduce the full bank (eqs 10–17).

    Args:
        up: the :class:`~gmjax.filters.gsf.GSUpdate` of the ``L·J`` models (child ``i J + j``).

    Returns:
        ``(mean (d,), cov (d, d), x̌ (d,), (i, j) (2,))``.
    """
    n_q, n_r, d = q_noise.capacity, r_noise.capacity, cfg.dim
    mu = up.mixture.weights.reshape(n_q, n_r)  # eq 9 (0 on padded slots)
    means = up.mixture.means.reshape(n_q, n_r, d)
    covs = up.mixture.covs.reshape(n_q, n_r, d, d)
    if cfg.method == "gsf-merge":  # eqs 10-11
        mean, cov = gmm.moments(up.mixture)
        return mean, cov, mean, jnp.full((2,), -1, jnp.int32)
    best = _argmax2(mu)  # eq 12
    if cfg.method == "gsf-remove":
        sel, x_check = best, means[best[0], best[1]]
    else:
        x_check = _merge(mu, means) if cfg.method == "red-gsfm" else means[best[0], best[1]]
        sel = _select(cfg.h_lin, _step_gain(cfg, q_noise), q_noise, r_noise, state.f_mean, x_check, z, inputs)
    return means[sel[0], sel[1]], covs[sel[0], sel[1]], x_check, sel  # eqs 13-14


def _initial_estimate(
    cfg: _Static,
    params: BankParams,
    q_noise: GaussianMixture,
    r_noise: GaussianMixture,
    state: BankState,
    z: Array,
    inputs: Any,
    preload_gain: tuple[Array, Array],
) -> tuple[Array, Array, Array]:
    """``x̌_k`` of ``red-pkg``, ``red-ssg``, ``red-dkg`` (§IV-A 3–5): ``(x̌, degenerate, repaired)``.

    Args:
        preload_gain: ``(K̄_k (d, m), S̄_k (m, m))`` of the preloaded-gain recursion.
    """
    if cfg.method in ("red-pkg", "red-ssg"):
        if cfg.method == "red-pkg":
            Kp, Sp = preload_gain
            shape = (q_noise.capacity, r_noise.capacity)
            K, S = jnp.broadcast_to(Kp, shape + Kp.shape), jnp.broadcast_to(Sp, shape + Sp.shape)
        else:
            assert state.ss_gain is not None and state.ss_innovation_cov is not None  # red-ssg: set in init
            K, S = state.ss_gain, state.ss_innovation_cov
        return _gain_estimate(
            cfg.h_lin,
            state.predicted,
            r_noise,
            _noise_log_weights(q_noise),
            _noise_log_weights(r_noise),
            K,
            S,
            z,
            inputs,
        )
    # red-dkg: one Kalman step on the moment-matched (step's) noises from (x̂_{k-1}, P_{k-1})
    q_mm_mean, q_mm_cov = gmm.moments(q_noise)
    kp = cfg.local.init(state.f_mean + q_mm_mean, gaussian.symmetrize(state.f_cov + q_mm_cov))
    kf, kinfo = cfg.local.update(kp, z, inputs, *gmm.moments(params.model.measurement_noise))
    return cfg.local.moments(kf)[0], jnp.zeros((), bool), kinfo.repaired


def _reduce_single(
    cfg: _Static,
    params: BankParams,
    q_noise: GaussianMixture,
    r_noise: GaussianMixture,
    state: BankState,
    z: Array,
    inputs: StepInputs,
    preload_gain: tuple[Array, Array],
) -> tuple[Array, ...]:
    """``matched``, ``kf-mm``, ``red-pkg``, ``red-ssg``, ``red-dkg``: choose ``(i, j)`` (eq 17 for
    the ``red-*``), then run that one Kalman filter (eqs 7–8).

    Returns:
        ``(mean, cov, x̌, (i, j), degenerate, repaired)``; ``x̌`` is the posterior mean for
        ``matched`` and ``kf-mm``.
    """
    degenerate = repaired = jnp.zeros((), bool)
    x_check = None
    if cfg.method == "matched":
        sel = _matched_pair(inputs.aux)
    elif cfg.method == "kf-mm":
        sel = jnp.zeros((2,), jnp.int32)
    else:
        x_check, degenerate, repaired = _initial_estimate(
            cfg, params, q_noise, r_noise, state, z, inputs, preload_gain
        )
        sel = _select(cfg.h_lin, _step_gain(cfg, q_noise), q_noise, r_noise, state.f_mean, x_check, z, inputs)
    mean, cov, rep = _one_update(cfg.local, state.predicted, r_noise, sel, z, inputs)
    return mean, cov, mean if x_check is None else x_check, sel, degenerate, repaired | rep


def _update(
    cfg: _Static, params: BankParams, state: BankState, z: Array, inputs: StepInputs
) -> tuple[BankState, StepInfo]:
    """The bank (eqs 7–9), the reduction of ``cfg.method`` and the preloaded-gain update."""
    q_noise, r_noise = _bank_noises(params.model, cfg.method, cfg.noise_at, inputs)
    z = jnp.asarray(z, state.mean.dtype)
    missing = is_missing(z)
    # the full bank of eqs 7-9 (its normaliser is the log-likelihood of every method)
    up = gs_update(cfg.local, state.predicted, z, inputs, r_noise)
    zs = jnp.where(missing, cfg.h_lin(state.mean, inputs)[0] + gmm.mean(r_noise), z)
    preload_post, Kp, Sp = _preload_update(
        cfg.h_lin, state.mean, state.preload_cov, _average_cov(r_noise), inputs
    )
    if cfg.method in _FULL_BANK:
        mean, cov, x_check, sel = _reduce_full(cfg, q_noise, r_noise, state, up, zs, inputs)
        degenerate, repaired = up.degenerate, up.repaired
    else:
        mean, cov, x_check, sel, degenerate, repaired = _reduce_single(
            cfg, params, q_noise, r_noise, state, zs, inputs, (Kp, Sp)
        )
    # predict-only step: the moment-matched prediction for every method
    mean = jnp.where(missing, state.mean, mean)
    cov, rep_c = repair_cov(jnp.where(missing, state.cov, cov))
    sel = jnp.where(missing, jnp.full((2,), -1, jnp.int32), sel)
    x_check = jnp.where(missing, state.mean, x_check)
    new = state._replace(mean=mean, cov=cov, preload_cov=jnp.where(missing, state.preload_cov, preload_post))
    flags = StepFlags(
        repaired=(repaired | rep_c) & ~missing,
        overflow=jnp.zeros((), bool),
        degenerate=degenerate & ~missing,
        nonfinite_measurement=missing,
    )
    info = StepInfo(
        mean=mean,
        cov=cov,
        loglik=up.loglik,
        n_components=jnp.ones((), jnp.int32),
        flags=flags,
        reduction=None,
        extra={"initial": x_check, "active": sel, "missing": missing},
    )
    return new, info


# ---------------------------------------------------------------------------------------------
# The builder.


def build_bank(
    model: StateSpaceModel,
    method: str,
    *,
    noise_gain: Any = "auto",
    ssg_iterations: int = 2000,
) -> Filter:
    """Build a linear GSF bank with one of the reductions of seed 004 (see the module docstring).

    Static (build-time) quantities: ``method``; the model's ``f`` and ``h`` (``F``, ``H`` are their
    Jacobians); ``G^+`` from ``noise_gain`` (``"auto"`` inspects the concrete process-noise
    covariances of ``model`` once, here); ``ssg_iterations``. Everything numeric is read from
    ``params`` (:class:`BankParams`) at each call; the Red-SSG steady-state gains are computed
    from ``params`` in ``init`` and carried in :class:`BankState`.

    Args:
        model: an affine :class:`~gmjax.models.StateSpaceModel`; its GM process and measurement
            noises are the ``L`` and ``J`` clusters of eqs 3–4 (padded slots allowed); its prior is
            moment-matched to one Gaussian. ``model.params`` becomes ``filter.params.model``.
        method: one of :data:`BANK_METHODS`.
        noise_gain: ``G`` ``(d, q)`` with ``v = G v_q`` for the process-noise term of eq 17;
            ``"auto"`` (default) detects it from the covariances (needs concrete arrays),
            ``None`` uses the full ``d``-dimensional density.
        ssg_iterations: Riccati steps for the steady-state gains of ``red-ssg``.

    Returns:
        A :class:`~gmjax.filters.Filter` over :class:`BankState` with :class:`BankParams`.
        ``update`` reads ``inputs.aux`` (``(2,)`` int true ``(i, j)``) for ``matched`` only. Its
        ``StepInfo``: ``mean``/``cov`` the reduced posterior, ``loglik`` the log of the eq-9
        normaliser (0 on a predict-only step), ``n_components = 1``, ``flags.repaired`` (a
        covariance was not numerically PD), ``flags.degenerate`` (every likelihood of eq 9
        underflowed: the prior weights ``w^i p^j`` were used), ``flags.overflow`` always False,
        ``reduction = None`` and ``extra``:

        * ``"initial"``: ``(d,)`` the initial estimate ``x̌_k`` of the active-cluster reduction
          (for the other methods the posterior mean);
        * ``"active"``: ``(2,)`` int32 ``(i, j)`` of the kept model; ``(-1, -1)`` for
          ``gsf-merge`` and on a predict-only step;
        * ``"missing"``: ``()`` bool, the measurement held a NaN or ``±inf`` (predict-only step;
          also ``flags.nonfinite_measurement``).

    Raises:
        ValueError: unknown ``method``, a bad model, ``noise_gain`` or ``ssg_iterations``; at
            trace time, ``matched`` without ``inputs.aux`` of shape ``(2,)``.
    """
    if method not in BANK_METHODS:
        raise ValueError(f"method: unknown {method!r}; expected one of {BANK_METHODS}")
    if isinstance(ssg_iterations, bool) or not isinstance(ssg_iterations, int) or ssg_iterations < 1:
        raise ValueError(f"ssg_iterations: must be a positive int, got {ssg_iterations!r}")
    check_model(model)
    f_step, h_step, _, _ = model.step_fns()  # f(x, inputs): t, dt and controls reach the model
    f_lin, h_lin = affine_parts(f_step), affine_parts(h_step)
    Gpinv = _resolve_noise_gain(noise_gain, model.process_noise) if method.startswith("red-") else None
    per_step_gain = (
        Gpinv is not None
        and isinstance(noise_gain, str)
        and model.process_noise_at is not None
        and Gpinv.shape[0] < model.state_dim
    )
    cfg = _Static(
        method,
        model.state_dim,
        f_lin,
        h_lin,
        linearized_filter(f_lin, h_lin),
        Gpinv,
        ssg_iterations,
        model.noise_at,
        Gpinv.shape[0] if per_step_gain and Gpinv is not None else None,
    )

    def init(
        params: BankParams, prior: GaussianMixture | None = None, *, key: PRNGKey | None = None
    ) -> BankState:
        del key
        return _init(cfg, params, prior)

    def predict(
        params: BankParams, state: BankState, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> BankState:
        del key
        return _predict(cfg, params, state, inputs)

    def update(
        params: BankParams, state: BankState, z: Array, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> tuple[BankState, StepInfo]:
        del key
        return _update(cfg, params, state, z, inputs)

    return Filter(init, predict, update, BankParams(model.params))


def sweep_errors(
    method: str,
    make_model: Callable[[Any], StateSpaceModel],
    simulate: Callable[[Any, Array], Any],
    params: Any,
    keys: Array,
    *,
    noise_gain: Any = None,
    position_dims: tuple[int, ...] = (0,),
    **bank_kwargs: Any,
) -> Array:
    """Position errors of one bank method over a grid of scenarios × Monte Carlo runs.

    ``vmap`` over the leading axis ``P`` of ``params`` (e.g. the noise-scale ``c`` of each KL
    point), ``vmap`` over the ``N`` run keys, ``lax.scan`` over time (:func:`gmjax.filters.run`,
    the true active clusters passed as ``inputs.aux``). Every method run with the same ``keys``
    sees the same simulated data (common random numbers). Wrap it in ``jax.jit`` with ``method``,
    ``make_model``, ``simulate`` static (one compiled kernel per method).

    Args:
        method: one of :data:`BANK_METHODS`.
        make_model: ``p -> StateSpaceModel`` (traceable in ``p``), e.g. from
            :func:`gmjax.scenarios.uwb_velocity.rwv_model`.
        simulate: ``(p, key) -> run`` with fields ``xs (T+1, d)``, ``zs (T, m)``, ``active (T, 2)``
            (:class:`gmjax.scenarios.uwb_velocity.LabeledRun`).
        params: a pytree whose leaves have a leading axis ``P``.
        keys: ``(N,)`` PRNG keys.
        noise_gain: passed to :func:`build_bank` (must be explicit or ``None`` under the trace).
        position_dims: the state components scored.

    Returns:
        ``(P, N, T, len(position_dims))`` estimate minus truth.
    """
    dims = jnp.asarray(position_dims)

    def one_point(p):
        filt = build_bank(make_model(p), method, noise_gain=noise_gain, **bank_kwargs)

        def one_run(key):
            sim = simulate(p, key)
            n_steps = sim.zs.shape[0]
            inputs = StepInputs(t=jnp.arange(1, n_steps + 1, dtype=jnp.int32), aux=sim.active)
            _, infos = run(filt, sim.zs, inputs)
            return infos.mean[:, dims] - sim.xs[1:, dims]

        return jax.vmap(one_run)(keys)

    return jax.vmap(one_point)(params)
