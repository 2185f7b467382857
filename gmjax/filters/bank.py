"""Linear Gaussian sum filters (banks of Kalman filters) with the reductions of seed 004.

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
``matched``       keep the *true* active cluster (oracle; needs ``active``, see below)
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

Readings where the paper is not explicit (each also stated where it is implemented):

* **Rank-deficient process noise.** In the random-walk-velocity model (eqs 20–22) ``v_k = G v``
  with scalar ``v`` and ``G = (dt, 1)^T``, so ``Q^i`` is rank one and ``N(v̌; u^i, Q^i)`` in eq 17
  is singular. With ``noise_gain=G`` the process-noise term of eq 17 is evaluated for the scalar
  ``G^+ v̌`` against ``N(G^+ u^i, G^+ Q^i G^{+T})`` (``G^+`` the pseudo-inverse); the default
  ``noise_gain="auto"`` finds ``G`` from the eigenvectors of ``sum_i w^i Q^i`` whose eigenvalues
  exceed ``1e-6`` of the largest (identity, i.e. the full density, when ``Q`` is full rank).
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
  at ``t = 1``; the model must be time invariant), found at build time by ``ssg_iterations``
  Riccati steps (checked against ``scipy.linalg.solve_discrete_are`` in the tests).
* **Red-DKG** (§IV-A 5): "the gain of a Kalman filter run at that iteration", computed from this
  filter's own ``P_{k-1}``; the Kalman filter of the paper's comparisons is the one on the
  moment-matched noises, so ``x̌_k`` is one such Kalman step from ``(x̂_{k-1}, P_{k-1})``. This
  matches §V-A: Red-DKG suffers where "a single Gaussian distribution cannot represent" the noise.
* **Matched** (§III-A): it keeps the cluster of the model that generated the data. The true
  ``(i, j)`` is passed per step as ``update(state, z, t, active=(i, j))`` (``run_bank`` takes an
  ``active`` array ``(T, 2)``; :func:`gmjax.models.seed004.simulate_labeled` produces it).
  Without ``active`` the matched filter raises ``ValueError``.
* **Missing measurement** (a NaN in ``z``): every method returns the moment-matched prediction.

Time indexing follows :func:`gmjax.filters.run`.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp

from gmjax import gaussian
from gmjax import mixture as gmm
from gmjax._types import Array
from gmjax.filters._core import (
    Filter,
    check_model,
    check_sequence,
    is_missing,
    kalman_gain,
    repair_cov,
    safe_chol,
)
from gmjax.filters.kalman import _affine_parts, _linearized_filter
from gmjax.mixture import GaussianMixture
from gmjax.models._base import StateSpaceModel

__all__ = [
    "BANK_METHODS",
    "BankState",
    "BankInfo",
    "build_bank",
    "run_bank",
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


class BankState(NamedTuple):
    """State of a linear GSF bank.

    Attributes:
        mean: ``(d,)`` after ``update`` the posterior ``x̂_{k|k}``; after ``predict`` the mean of the
            predicted mixture.
        cov: ``(d, d)`` the matching covariance.
        pred_means: ``(L, d)`` ``F x̂_{k-1} + u^i`` (one per process-noise cluster).
        pred_covs: ``(L, d, d)`` ``F P_{k-1} F^T + Q^i``.
        f_mean: ``(d,)`` ``F x̂_{k-1}`` (the reference point of eq 15).
        f_cov: ``(d, d)`` ``F P_{k-1} F^T`` (Red-DKG adds the moment-matched ``Q`` to it).
        preload_cov: ``(d, d)`` the data-independent covariance of the preloaded-gain recursion
            (Red-PKG; posterior after ``update``, prediction after ``predict``).
    """

    mean: Array
    cov: Array
    pred_means: Array
    pred_covs: Array
    f_mean: Array
    f_cov: Array
    preload_cov: Array


class BankInfo(NamedTuple):
    """Per-step report.

    Attributes:
        mean, cov: ``(d,)``, ``(d, d)`` the reduced posterior.
        initial: ``(d,)`` the initial estimate ``x̌_k`` of the active-cluster reduction (for the
            other methods: the posterior mean).
        active: ``(2,)`` int32 ``(i, j)`` of the kept model; ``(-1, -1)`` for ``gsf-merge`` and on a
            predict-only step.
        repaired: ``()`` bool, a covariance was repaired (not numerically positive definite).
        degenerate: ``()`` bool, every model's likelihood underflowed (the prior weights ``w^i p^j``
            were used in eq 9 instead).
        missing: ``()`` bool, the measurement held a NaN (predict-only step).
    """

    mean: Array
    cov: Array
    initial: Array
    active: Array
    repaired: Array
    degenerate: Array
    missing: Array


def _noise_log_weights(noise: GaussianMixture) -> Array:
    lw = gmm.log_weights(noise)
    return jnp.where(noise.mask, lw - logsumexp(lw), -jnp.inf)


def _riccati_step(P: Array, F: Array, H: Array, Q: Array, R: Array) -> tuple[Array, Array, Array]:
    """One predict + update of the covariance: ``(P_post, K, S)`` from the previous posterior ``P``."""
    Pp = gaussian.symmetrize(F @ P @ F.T + Q)
    S = gaussian.symmetrize(H @ Pp @ H.T + R)
    K = kalman_gain(Pp @ H.T, safe_chol(S).factor)
    A = jnp.eye(P.shape[0], dtype=P.dtype) - K @ H
    return gaussian.symmetrize(A @ Pp @ A.T + K @ R @ K.T), K, S


def steady_state_gains(F: Array, H: Array, Q: Array, R: Array, P0: Array, *, iterations: int = 2000):
    """Steady-state Kalman gain and innovation covariance of ``(F, H, Q, R)`` (traceable).

    Iterates the Riccati recursion ``iterations`` times from ``P0`` (a ``lax.fori_loop``).

    Returns:
        ``(K (d, m), S (m, m))``.
    """
    P = jax.lax.fori_loop(0, iterations, lambda _, P: _riccati_step(P, F, H, Q, R)[0], P0)
    _, K, S = _riccati_step(P, F, H, Q, R)
    return K, S


def _resolve_noise_gain(noise_gain: Any, noise: GaussianMixture) -> Array:
    """The pseudo-inverse ``G^+`` ``(q, d)`` used for the process-noise term of eq 17."""
    d = noise.dim
    dtype = noise.means.dtype
    if isinstance(noise_gain, str):
        if noise_gain != "auto":
            raise ValueError(f"noise_gain: expected 'auto', None or a (d, q) array, got {noise_gain!r}")
        if isinstance(noise.covs, jax.core.Tracer) or isinstance(noise.weights, jax.core.Tracer):
            raise ValueError(
                "noise_gain: 'auto' needs concrete process-noise covariances; under a trace pass "
                "noise_gain explicitly (a (d, q) array, or None for the full density)"
            )
        w = np.where(np.asarray(noise.mask), np.asarray(noise.weights, float), 0.0)
        Qbar = np.einsum("k,kij->ij", w / w.sum(), np.asarray(noise.covs, float))
        evals, evecs = np.linalg.eigh(Qbar)
        keep = evals > 1e-6 * evals.max()
        if keep.all():
            return jnp.eye(d, dtype=dtype)
        return jnp.asarray(np.linalg.pinv(evecs[:, keep]), dtype)
    if noise_gain is None:
        return jnp.eye(d, dtype=dtype)
    G = jnp.asarray(noise_gain, dtype)
    if G.ndim != 2 or G.shape[0] != d or G.shape[1] > d or G.shape[1] < 1:
        raise ValueError(f"noise_gain: expected shape ({d}, q) with 1 <= q <= {d}, got {G.shape}")
    return jnp.linalg.pinv(G)


def build_bank(
    model: StateSpaceModel,
    method: str,
    *,
    noise_gain: Any = "auto",
    ssg_iterations: int = 2000,
) -> Filter:
    """Build a linear GSF bank with one of the reductions of seed 004 (see the module docstring).

    Args:
        model: an affine :class:`~gmjax.models.StateSpaceModel` (``F``, ``H`` are the Jacobians of
            ``f``, ``h``); its GM process and measurement noises are the ``L`` and ``J`` clusters of
            eqs 3–4 (padded slots allowed); its prior is moment-matched to one Gaussian.
        method: one of :data:`BANK_METHODS`.
        noise_gain: ``G`` ``(d, q)`` with ``v = G v_q`` for the process-noise term of eq 17;
            ``"auto"`` (default) detects it from the covariances (needs concrete arrays),
            ``None`` uses the full ``d``-dimensional density.
        ssg_iterations: Riccati steps for the steady-state gains of ``red-ssg`` (static).

    Returns:
        ``Filter(init, predict, update, moments)``: ``init(prior=None) -> BankState``,
        ``predict(state, t)``, ``update(state, z, t, active=None) -> (BankState, BankInfo)``
        (``active``: ``(2,)`` int ``(i, j)`` true clusters, required by ``matched`` only),
        ``moments(state) -> (mean, cov)``.

    Raises:
        ValueError: unknown ``method``, a bad model or ``noise_gain``.
    """
    if method not in BANK_METHODS:
        raise ValueError(f"method: unknown {method!r}; expected one of {BANK_METHODS}")
    if not isinstance(ssg_iterations, int) or ssg_iterations < 1:
        raise ValueError(f"ssg_iterations: must be a positive int, got {ssg_iterations!r}")
    check_model(model)
    d, m = model.state_dim, model.measurement_dim
    dtype = model.prior.means.dtype
    q_noise, r_noise = model.process_noise, model.measurement_noise
    if method == "kf-mm":
        q_noise = gmm.from_gaussian(*gmm.moments(q_noise))
        r_noise = gmm.from_gaussian(*gmm.moments(r_noise))
    Gpinv = _resolve_noise_gain(noise_gain, q_noise) if method.startswith("red-") else None
    q_lw, r_lw = _noise_log_weights(q_noise), _noise_log_weights(r_noise)
    q_means, q_covs = q_noise.means, q_noise.covs
    r_means, r_covs = r_noise.means, r_noise.covs
    q_mm_mean, q_mm_cov = gmm.moments(model.process_noise)
    r_mm_mean, r_mm_cov = gmm.moments(model.measurement_noise)
    # within-cluster averages for the preloaded gains (Red-PKG)
    q_bar = jnp.einsum("k,kij->ij", jnp.exp(q_lw), q_covs)
    r_bar = jnp.einsum("k,kij->ij", jnp.exp(r_lw), r_covs)
    local = _linearized_filter(_affine_parts(model.f), _affine_parts(model.h))
    f_lin = _affine_parts(model.f)
    h_lin = _affine_parts(model.h)
    L, J = q_means.shape[0], r_means.shape[0]

    if method == "red-ssg":
        t1 = jnp.ones((), jnp.int32)
        F1 = f_lin(jnp.zeros((d,), dtype), t1)[1]
        H1 = h_lin(jnp.zeros((d,), dtype), t1)[1]
        P0 = gmm.cov(model.prior)
        pair = jax.vmap(jax.vmap(
            lambda Q, R: steady_state_gains(F1, H1, Q, R, P0, iterations=ssg_iterations), (None, 0)), (0, None))
        ss_K, ss_S = pair(q_covs, r_covs)  # (L, J, d, m), (L, J, m, m)
    else:
        ss_K = ss_S = None

    def init(prior: GaussianMixture | None = None) -> BankState:
        prior = model.prior if prior is None else prior
        if not isinstance(prior, GaussianMixture):
            raise ValueError(f"prior: expected a GaussianMixture, got {type(prior).__name__}")
        mean, cov = gmm.moments(prior)
        mean = mean.astype(dtype)
        cov = cov.astype(dtype)
        return BankState(
            mean, cov, jnp.broadcast_to(mean, (L, d)), jnp.broadcast_to(cov, (L, d, d)), mean, cov, cov
        )

    def predict(state: BankState, t: Array) -> BankState:
        fm, F = f_lin(state.mean, t)
        x0 = local.init(state.mean, state.cov)
        one = lambda qm, qP: local.moments(local.predict(x0, t, qm, qP))  # noqa: E731
        means, covs = jax.vmap(one)(q_means, q_covs)
        mix = GaussianMixture(jnp.exp(q_lw), means, covs, q_noise.mask)
        mean, cov = gmm.moments(mix)
        preload = gaussian.symmetrize(F @ state.preload_cov @ F.T + q_bar)
        f_cov = gaussian.symmetrize(F @ state.cov @ F.T)
        return BankState(mean, cov, means, covs, fm, f_cov, preload)

    def _one_update(state: BankState, i, j, z, t):
        st = local.init(state.pred_means[i], state.pred_covs[i])
        new, info = local.update(st, z, t, r_means[j], r_covs[j])
        mean, cov = local.moments(new)
        return mean, cov, info.loglik, info.repaired

    def _full_bank(state: BankState, z, t):
        ii, jj = jnp.meshgrid(jnp.arange(L), jnp.arange(J), indexing="ij")
        means, covs, ll, rep = jax.vmap(jax.vmap(lambda i, j: _one_update(state, i, j, z, t)))(ii, jj)
        return means, covs, ll, rep  # (L, J, d), (L, J, d, d), (L, J), (L, J)

    def _weights(ll):
        """Eq 9 in the log domain; ``(log mu (L, J), degenerate)``."""
        log_prior = q_lw[:, None] + r_lw[None, :]
        log_w = log_prior + ll
        norm = logsumexp(log_w)
        degenerate = ~jnp.isfinite(norm)
        log_w = jnp.where(degenerate, log_prior, log_w - jnp.where(degenerate, 0.0, norm))
        return log_w, degenerate

    def _merge(log_mu, means):
        mu = jnp.where(jnp.isfinite(log_mu), jnp.exp(log_mu), 0.0)
        return jnp.einsum("ij,ijd->d", mu, means)

    def _argmax2(score):
        flat = jnp.argmax(score.reshape(-1))
        return jnp.stack([flat // J, flat % J]).astype(jnp.int32)

    def _gain_estimate(state, z, t, K, S):
        """GSF-merge mean with given gains: ``K``, ``S`` of shape ``(L, J, d, m)``, ``(L, J, m, m)``."""

        def one(i, j):
            xp = state.pred_means[i]
            zh = h_lin(xp, t)[0] + r_means[j]
            y = z - zh
            Lc = safe_chol(S[i, j])
            r = jax.scipy.linalg.solve_triangular(Lc.factor, y, lower=True)
            ll = -0.5 * (m * jnp.log(2 * jnp.pi) + r @ r) - jnp.sum(jnp.log(jnp.abs(jnp.diagonal(Lc.factor))))
            return xp + K[i, j] @ y, ll, Lc.repaired

        ii, jj = jnp.meshgrid(jnp.arange(L), jnp.arange(J), indexing="ij")
        xs, ll, rep = jax.vmap(jax.vmap(one))(ii, jj)
        log_mu, degenerate = _weights(ll)
        return _merge(log_mu, xs), degenerate, jnp.any(rep)

    def _select(state, x_check, z, t):
        """Eqs 15–17: ``(i*, j*)`` from the initial estimate ``x_check``."""
        v = Gpinv @ (x_check - state.f_mean)  # eq 15 (projected on the noise subspace)
        w = z - h_lin(x_check, t)[0]  # eq 16
        qm = q_means @ Gpinv.T
        qc = jnp.einsum("ab,kbc,dc->kad", Gpinv, q_covs, Gpinv)
        lv = q_lw + jax.vmap(lambda mu, P: gaussian.logpdf(v, mu, P))(qm, qc)
        lw = r_lw + jax.vmap(lambda mu, P: gaussian.logpdf(w, mu, P))(r_means, r_covs)
        lv = jnp.where(q_noise.mask, lv, -jnp.inf)
        lw = jnp.where(r_noise.mask, lw, -jnp.inf)
        return jnp.stack([jnp.argmax(lv), jnp.argmax(lw)]).astype(jnp.int32)

    def update(state: BankState, z: Array, t: Array, active: Array | None = None):
        z = jnp.asarray(z, dtype)
        missing = is_missing(z)
        zs = jnp.where(missing, h_lin(state.mean, t)[0] + gmm.mean(r_noise), z)
        # the preloaded-gain covariance recursion (data independent)
        _, Hc = h_lin(state.mean, t)
        Sp = gaussian.symmetrize(Hc @ state.preload_cov @ Hc.T + r_bar)
        Kp = kalman_gain(state.preload_cov @ Hc.T, safe_chol(Sp).factor)
        Ap = jnp.eye(d, dtype=dtype) - Kp @ Hc
        preload_post = gaussian.symmetrize(Ap @ state.preload_cov @ Ap.T + Kp @ r_bar @ Kp.T)
        degenerate = jnp.zeros((), bool)
        repaired = jnp.zeros((), bool)

        if method in ("gsf-merge", "gsf-remove", "red-gsfm", "red-gsfr"):
            means, covs, ll, rep = _full_bank(state, zs, t)
            log_mu, degenerate = _weights(ll)
            repaired = jnp.any(rep)
            if method == "gsf-merge":  # eqs 10-11
                mu = jnp.where(jnp.isfinite(log_mu), jnp.exp(log_mu), 0.0)
                mix = GaussianMixture(mu.reshape(-1), means.reshape(-1, d), covs.reshape(-1, d, d),
                                      jnp.isfinite(log_mu).reshape(-1))
                mean, cov = gmm.moments(mix)
                x_check, sel = mean, jnp.full((2,), -1, jnp.int32)
            else:
                best = _argmax2(log_mu)  # eq 12
                if method == "gsf-remove":
                    sel = best
                    x_check = means[best[0], best[1]]
                else:
                    x_check = _merge(log_mu, means) if method == "red-gsfm" else means[best[0], best[1]]
                    sel = _select(state, x_check, zs, t)
                mean, cov = means[sel[0], sel[1]], covs[sel[0], sel[1]]  # eqs 13-14
        else:
            if method == "matched":
                if active is None:
                    raise ValueError(
                        "active: the 'matched' filter needs the true active clusters, "
                        "update(state, z, t, active=(i, j)) / run_bank(..., active=(T, 2) array)"
                    )
                sel = jnp.asarray(active, jnp.int32).reshape(2)
                x_check = None
            elif method == "kf-mm":
                sel = jnp.zeros((2,), jnp.int32)
                x_check = None
            elif method == "red-pkg":
                K = jnp.broadcast_to(Kp, (L, J, d, m))
                S = jnp.broadcast_to(Sp, (L, J, m, m))
                x_check, degenerate, rep = _gain_estimate(state, zs, t, K, S)
                repaired = repaired | rep
                sel = _select(state, x_check, zs, t)
            elif method == "red-ssg":
                x_check, degenerate, rep = _gain_estimate(state, zs, t, ss_K, ss_S)
                repaired = repaired | rep
                sel = _select(state, x_check, zs, t)
            else:  # red-dkg: one Kalman step on the moment-matched noises from (x̂_{k-1}, P_{k-1})
                kp_cov = gaussian.symmetrize(state.f_cov + q_mm_cov)
                kf, kinfo = local.update(local.init(state.f_mean + q_mm_mean, kp_cov), zs, t, r_mm_mean, r_mm_cov)
                x_check = local.moments(kf)[0]
                repaired = repaired | kinfo.repaired
                sel = _select(state, x_check, zs, t)
            mean, cov, _, rep = _one_update(state, sel[0], sel[1], zs, t)
            repaired = repaired | rep
            if x_check is None:
                x_check = mean

        # predict-only step: the moment-matched prediction for every method
        mean = jnp.where(missing, state.mean, mean)
        cov = jnp.where(missing, state.cov, cov)
        cov, rep_c = repair_cov(cov)
        preload_post = jnp.where(missing, state.preload_cov, preload_post)
        sel = jnp.where(missing, jnp.full((2,), -1, jnp.int32), sel)
        x_check = jnp.where(missing, state.mean, x_check)
        new = BankState(mean, cov, state.pred_means, state.pred_covs, state.f_mean, state.f_cov, preload_post)
        info = BankInfo(
            mean=mean, cov=cov, initial=x_check, active=sel,
            repaired=(repaired | rep_c) & ~missing, degenerate=degenerate & ~missing, missing=missing,
        )
        return new, info

    def moments(state: BankState) -> tuple[Array, Array]:
        return state.mean, state.cov

    return Filter(init, predict, update, moments)


def run_bank(
    filter: Filter,
    zs: Array,
    ts: Array | None = None,
    *,
    active: Array | None = None,
    prior: GaussianMixture | None = None,
) -> tuple[BankState, BankInfo]:
    """Run a bank filter over ``zs`` ``(T, m)`` with ``lax.scan`` (like :func:`gmjax.filters.run`).

    Args:
        filter: from :func:`build_bank`.
        zs: ``(T, m)`` measurements (a row with a NaN is a predict-only step).
        ts: ``(T,)`` times, default ``1..T``.
        active: ``(T, 2)`` int true clusters ``(i, j)`` per step; required by ``matched``,
            ignored by the other methods.
        prior: prior mixture (default the model's).

    Returns:
        ``(states, infos)`` with a leading ``T`` axis.
    """
    zs, ts = check_sequence(zs, ts)
    T = zs.shape[0]
    if active is not None:
        active = jnp.asarray(active)
        if active.shape != (T, 2):
            raise ValueError(f"active: expected shape ({T}, 2), got {active.shape}")
    state0 = filter.init(prior)

    def step(state, inp):
        z, t, a = inp
        state = filter.predict(state, t)
        state, info = filter.update(state, z, t, active=a)
        return state, (state, info)

    _, (states, infos) = jax.lax.scan(step, state0, (zs, ts, active))
    return states, infos


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
    point), ``vmap`` over the ``N`` run keys, ``lax.scan`` over time. Every method run with the
    same ``keys`` sees the same simulated data (common random numbers). Wrap it in ``jax.jit``
    with ``method``, ``make_model``, ``simulate`` static (one compiled kernel per method).

    Args:
        method: one of :data:`BANK_METHODS`.
        make_model: ``p -> StateSpaceModel`` (traceable in ``p``), e.g. from
            :func:`gmjax.models.seed004.rwv_model`.
        simulate: ``(p, key) -> run`` with fields ``xs (T+1, d)``, ``zs (T, m)``, ``active (T, 2)``
            (:class:`gmjax.models.seed004.LabeledRun`).
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
            run = simulate(p, key)
            _, infos = run_bank(filt, run.zs, active=run.active)
            return infos.mean[:, dims] - run.xs[1:, dims]

        return jax.vmap(one_run)(keys)

    return jax.vmap(one_point)(params)
