"""The numerical pieces of one step of seed 004's linear Gaussian sum filter bank (Pishdad & Labeau 2014).

:mod:`gmjax.filters.bank` assembles its ``init``, ``predict`` and ``update`` from these pure functions: the
cluster weights and moment-matched noises derived from the parameters, ``G^+`` of eq 17 (from
``noise_gain``, and per step from the process noise), the eq-9 weights, the merged mean of eq 10, the
Kalman posterior of one model ``M^{ij}`` (eqs 7–8), the preloaded-gain update (Red-PKG), the GSF-merge
estimate with given gains (Red-PKG, Red-SSG), the active-cluster selection of eqs 15–17, and the static
(build-time) part of a bank that the step functions read. The equations, and the readings where the paper
is not explicit, are documented in :mod:`gmjax.filters.bank`.
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
from gmjax.filters._core import LocalFilter, kalman_gain, safe_chol
from gmjax.mixture import GaussianMixture
from gmjax.models.base import ModelParams

Linearize = Callable[[Array, Any], tuple[Array, Array]]  # (x, inputs) -> (value, Jacobian)


# ---------------------------------------------------------------------------------------------
# Quantities derived from the parameters (computed at call time).


def _noise_log_weights(noise: GaussianMixture) -> Array:
    """Normalised log weights ``(n,)`` of a noise mixture, ``-inf`` on padded slots."""
    lw = gmm.log_weights(noise)
    return jnp.where(noise.mask, lw - logsumexp(lw), -jnp.inf)


def _bank_noises(
    model: ModelParams, method: str, noise_at: Callable | None = None, inputs: Any = None
) -> tuple[GaussianMixture, GaussianMixture]:
    """The bank's process and measurement clusters: the model's (the process noise at the step's
    ``inputs`` through ``noise_at``, e.g. ``Q(dt)``), or for ``kf-mm`` their moments."""
    q_noise, r_noise = model.process_noise, model.measurement_noise
    if noise_at is not None and inputs is not None:
        q_noise = noise_at(q_noise, inputs)
    if method == "kf-mm":
        q_noise = gmm.from_gaussian(*gmm.moments(q_noise))
        r_noise = gmm.from_gaussian(*gmm.moments(r_noise))
    return q_noise, r_noise


def _average_cov(noise: GaussianMixture) -> Array:
    """The within-cluster average ``sum_i w^i Q^i`` ``(k, k)`` (``Q̄``, ``R̄`` of Red-PKG)."""
    return jnp.einsum("k,kij->ij", jnp.exp(_noise_log_weights(noise)), noise.covs)


def _resolve_noise_gain(noise_gain: Any, noise: GaussianMixture) -> Array:
    """The pseudo-inverse ``G^+`` ``(q, d)`` used for the process-noise term of eq 17 (static)."""
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


# ---------------------------------------------------------------------------------------------
# The pieces of one step (pure functions).


def _eq9_log_weights(q_lw: Array, r_lw: Array, ll: Array) -> tuple[Array, Array]:
    """Eq 9 in the log domain from the ``(L, J)`` log-likelihoods ``ll``: ``(log mu, degenerate)``.

    If every likelihood underflows the prior weights ``w^i p^j`` are used and ``degenerate`` is set.
    """
    log_prior = q_lw[:, None] + r_lw[None, :]
    log_w = log_prior + ll
    norm = logsumexp(log_w)
    degenerate = ~jnp.isfinite(norm)
    log_w = jnp.where(degenerate, log_prior, log_w - jnp.where(degenerate, 0.0, norm))
    return log_w, degenerate


def _merge(mu: Array, means: Array) -> Array:
    """The merged mean of eq 10, ``sum_ij mu^{ij} x̂^{ij}`` ``(d,)`` from the ``(L, J)`` weights."""
    return jnp.einsum("ij,ijd->d", mu, means)


def _weights_from_log(log_mu: Array) -> Array:
    """``mu = exp(log mu)``, 0 where ``log mu = -inf`` (padded slots)."""
    return jnp.where(jnp.isfinite(log_mu), jnp.exp(log_mu), 0.0)


def _argmax2(score: Array) -> Array:
    """``(2,)`` int32 ``(i, j)`` of the largest entry of an ``(L, J)`` score (eq 12)."""
    flat = jnp.argmax(score.reshape(-1))
    J = score.shape[1]
    return jnp.stack([flat // J, flat % J]).astype(jnp.int32)


def _one_update(
    local: LocalFilter,
    predicted: GaussianMixture,
    r_noise: GaussianMixture,
    sel: Array,
    z: Array,
    inputs: Any,
) -> tuple[Array, Array, Array]:
    """Kalman posterior of model ``M^{ij}`` (eqs 7–8) for ``sel = (i, j)``: ``(mean, cov, repaired)``."""
    i, j = sel[0], sel[1]
    st = local.init(predicted.means[i], predicted.covs[i])
    new, info = local.update(st, z, inputs, r_noise.means[j], r_noise.covs[j])
    mean, cov = local.moments(new)
    return mean, cov, info.repaired


def _preload_update(
    h_lin: Linearize, mean: Array, preload_cov: Array, r_bar: Array, inputs: Any
) -> tuple[Array, Array, Array]:
    """The data-independent update of the preloaded-gain recursion (Red-PKG, §IV-A 3).

    Returns:
        ``(P̄_{k|k} (d, d), K̄_k (d, m), S̄_k (m, m))``.
    """
    _, Hc = h_lin(mean, inputs)
    Sp = gaussian.symmetrize(Hc @ preload_cov @ Hc.T + r_bar)
    Kp = kalman_gain(preload_cov @ Hc.T, safe_chol(Sp).factor)
    Ap = jnp.eye(mean.shape[0], dtype=mean.dtype) - Kp @ Hc
    return gaussian.symmetrize(Ap @ preload_cov @ Ap.T + Kp @ r_bar @ Kp.T), Kp, Sp


def _gain_estimate(
    h_lin: Linearize,
    predicted: GaussianMixture,
    r_noise: GaussianMixture,
    q_lw: Array,
    r_lw: Array,
    K: Array,
    S: Array,
    z: Array,
    inputs: Any,
) -> tuple[Array, Array, Array]:
    """GSF-merge mean (eqs 9–10) with given gains (Red-PKG, Red-SSG).

    Args:
        K: ``(L, J, d, m)`` the gain of every model.
        S: ``(L, J, m, m)`` its innovation covariance (also in the eq 9 weights).

    Returns:
        ``(x̌ (d,), degenerate, repaired)``.
    """
    m = z.shape[0]

    def one(i, j):
        xp = predicted.means[i]
        y = z - (h_lin(xp, inputs)[0] + r_noise.means[j])
        Lc = safe_chol(S[i, j])
        r = gaussian.solve_lower(Lc.factor, y)
        ll = -0.5 * (m * jnp.log(2 * jnp.pi) + r @ r) - jnp.sum(jnp.log(jnp.abs(jnp.diagonal(Lc.factor))))
        return xp + K[i, j] @ y, ll, Lc.repaired

    ii, jj = jnp.meshgrid(jnp.arange(K.shape[0]), jnp.arange(K.shape[1]), indexing="ij")
    xs, ll, rep = jax.vmap(jax.vmap(one))(ii, jj)
    log_mu, degenerate = _eq9_log_weights(q_lw, r_lw, ll)
    return _merge(_weights_from_log(log_mu), xs), degenerate, jnp.any(rep)


def _select(
    h_lin: Linearize,
    Gpinv: Array,
    q_noise: GaussianMixture,
    r_noise: GaussianMixture,
    f_mean: Array,
    x_check: Array,
    z: Array,
    inputs: Any,
) -> Array:
    """Eqs 15–17: ``(i*, j*)`` ``(2,)`` int32 from the initial estimate ``x_check``."""
    v = Gpinv @ (x_check - f_mean)  # eq 15 (projected on the noise subspace)
    w = z - h_lin(x_check, inputs)[0]  # eq 16
    qm = q_noise.means @ Gpinv.T
    qc = jnp.einsum("ab,kbc,dc->kad", Gpinv, q_noise.covs, Gpinv)
    lv = _noise_log_weights(q_noise) + jax.vmap(lambda mu, P: gaussian.logpdf(v, mu, P))(qm, qc)
    lw = _noise_log_weights(r_noise) + jax.vmap(lambda mu, P: gaussian.logpdf(w, mu, P))(
        r_noise.means, r_noise.covs
    )
    lv = jnp.where(q_noise.mask, lv, -jnp.inf)
    lw = jnp.where(r_noise.mask, lw, -jnp.inf)
    return jnp.stack([jnp.argmax(lv), jnp.argmax(lw)]).astype(jnp.int32)


def _matched_pair(aux: Any) -> Array:
    """The true pair ``(i, j)`` of ``inputs.aux`` for ``matched``; clear errors at trace time."""
    if aux is None:
        raise ValueError(
            "inputs.aux: the 'matched' filter needs the true active cluster pair (i, j) of every "
            "step: gmjax.filters.run(filt, zs, StepInputs(t=ts, aux=active)) with active a (T, 2) "
            "int array (gmjax.scenarios.uwb_velocity.simulate_labeled returns it)"
        )
    if jnp.shape(aux) != (2,):
        raise ValueError(
            f"inputs.aux: the 'matched' filter expects the active pair (i, j) of shape (2,) per step "
            f"((T, 2) over a run), got shape {jnp.shape(aux)}"
        )
    return jnp.asarray(aux, jnp.int32)


# ---------------------------------------------------------------------------------------------
# The static part of a bank, read by the step functions of gmjax.filters.bank.


class _Static(NamedTuple):
    """The static (build-time) part of a bank: code and structure, no parameter values."""

    method: str
    dim: int
    f_lin: Linearize  # x, inputs -> (f(x, inputs), F)
    h_lin: Linearize  # x, inputs -> (h(x, inputs), H)
    local: LocalFilter  # the Kalman filter of one model M^{ij}
    Gpinv: Array | None  # (q, d) G^+ of eq 17 (red-* only)
    ssg_iterations: int
    noise_at: Callable[[GaussianMixture, Any], GaussianMixture]  # the step's process noise (Q(dt))
    gain_rank: int | None  # q: re-derive G^+ from each step's noise (auto gain with process_noise_at)


def _step_gain(cfg: _Static, q_noise: GaussianMixture) -> Array:
    """``G^+`` ``(q, d)`` of eq 17 for this step: the static one, or (``noise_gain="auto"`` with a
    per-step process noise) an orthonormal basis of the ``q`` leading eigenvectors of the step's
    ``sum_i w^i Q^i`` (``q`` fixed at build time), so a noise subspace that moves with ``dt``
    (``G = (dt, 1)^T``) is followed."""
    assert cfg.Gpinv is not None  # set for every red-* method
    if cfg.gain_rank is None:
        return cfg.Gpinv
    _, evecs = jnp.linalg.eigh(_average_cov(q_noise))
    return evecs[:, -cfg.gain_rank :].T
