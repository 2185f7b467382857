"""Sigma-point Kalman filters (UKF, CKF, GHKF, sparse-grid) and the square-root cubature KF.

One core, :func:`local_sigma`, is parameterised by a :class:`gmjax.quadrature.SigmaPoints` rule
for ``N(0, I)``:

* predict: ``X_i = m + L z_i`` (``P = L L^T``), ``Y_i = f(X_i, t)``,
  ``m' = sum wm_i Y_i + q_mean``, ``P' = sum wc_i (Y_i - m'_0)(Y_i - m'_0)^T + Q``
  (seed 002 eqs 30–32; seed 001 eqs 8–10 for the cubature rule);
* update: points are **redrawn** from the predicted ``(m', P')`` (seed 001 eq 13),
  ``Z_i = h(X_i, t)``, ``z_hat = sum wm_i Z_i + r_mean``, ``S = sum wc_i dZ dZ^T + R``,
  ``Pxz = sum wc_i (X_i - m')(Z_i - z_hat_0)^T``, ``K = Pxz S^{-1}``, ``m+ = m' + K (z - z_hat)``,
  ``P+ = P' - K S K^T``.

Note: FilterPy's ``UnscentedKalmanFilter`` / ``CubatureKalmanFilter`` instead reuse the propagated
points ``f(X_i)`` in the update; with process noise the two differ. gmjax follows the papers
(redraw), which is also what makes the update depend on the predicted Gaussian only — a
requirement of Gaussian sum filters, whose components are re-created between predict and update.

:func:`local_sckf` is the square-root cubature KF of seed 001 eqs 8–22: it carries the lower
Cholesky factor ``S`` (:class:`SqrtState`) and re-triangularises with a QR decomposition
(``Tria``), never forming a covariance.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular

from gmjax import gaussian
from gmjax import quadrature
from gmjax.filters._core import (
    Filter,
    GaussianState,
    LocalFilter,
    SqrtState,
    check_model,
    finish_info,
    from_local,
    gaussian_state_init,
    gaussian_state_moments,
    kalman_gain,
    loglik_from_chol,
    repair_cov,
    safe_chol,
    safe_z,
    select_state,
)
from gmjax.models._base import StateSpaceModel
from gmjax.quadrature import SigmaPoints

__all__ = [
    "local_sigma",
    "local_ukf",
    "local_ckf",
    "local_ghkf",
    "local_sgkf",
    "local_sckf",
    "build_sigma",
    "build_ukf",
    "build_ckf",
    "build_ghkf",
    "build_sgkf",
    "build_sckf",
    "tria",
]


def _check_rule(rule) -> SigmaPoints:
    if not isinstance(rule, SigmaPoints):
        raise ValueError(f"rule: expected a quadrature.SigmaPoints, got {type(rule).__name__}")
    return rule


def _rule_getter(rule):
    """``(d, dtype) -> SigmaPoints`` from a fixed rule or a constructor ``(d, dtype) -> rule``.

    The rule size is static, so constructors are called at trace time with the state's
    dimension and dtype; results are cached.
    """
    if isinstance(rule, SigmaPoints):

        def get(d, dtype):
            if rule.dim != d:
                raise ValueError(
                    f"rule: dimension {rule.dim} does not match the state dimension {d}"
                )
            return SigmaPoints(*(a.astype(dtype) for a in rule))

        return get
    if not callable(rule):
        raise ValueError(
            f"rule: expected a SigmaPoints or a callable (d, dtype) -> SigmaPoints, got {rule!r}"
        )
    cache = {}

    def get(d, dtype):
        key = (int(d), jnp.dtype(dtype).name)
        if key not in cache:
            # built eagerly even when first requested inside a trace, so the cache never
            # holds a tracer
            with jax.ensure_compile_time_eval():
                cache[key] = _check_rule(rule(int(d), jnp.dtype(dtype)))
        return cache[key]

    return get


def _weighted_cov(wc, A, B):
    """``sum_i wc_i A_i B_i^T`` for ``A (n, a)``, ``B (n, b)``."""
    return jnp.einsum("n,ni,nj->ij", wc, A, B)


def local_sigma(f, h, rule) -> LocalFilter:
    """Sigma-point Kalman filter with the quadrature ``rule`` (see the module docstring).

    Args:
        f: ``f(x (d,), t) -> (d,)``.
        h: ``h(x (d,), t) -> (m,)``.
        rule: a :class:`SigmaPoints` for ``N(0, I_d)``, or a constructor
            ``(d, dtype) -> SigmaPoints`` called at trace time with the state's size.

    Returns:
        A :class:`LocalFilter` over :class:`GaussianState`. The update's ``repaired`` flag is set
        when the predicted covariance, ``S`` or the posterior covariance needed jitter.
    """
    get_rule = _rule_getter(rule)
    fv = jax.vmap(f, in_axes=(0, None))
    hv = jax.vmap(h, in_axes=(0, None))

    def predict(state: GaussianState, t, noise_mean, noise_cov) -> GaussianState:
        rule = get_rule(state.mean.shape[-1], state.mean.dtype)
        wm, wc = rule.wm, rule.wc
        X = quadrature.transform(rule, state.mean, safe_chol(state.cov).factor, is_chol=True)
        Y = fv(X, t)
        mean0 = wm @ Y
        dY = Y - mean0
        cov = gaussian.symmetrize(_weighted_cov(wc, dY, dY) + noise_cov)
        return GaussianState(mean0 + noise_mean, cov)

    def update(state: GaussianState, z, t, noise_mean, noise_cov):
        m, P = state
        rule = get_rule(m.shape[-1], m.dtype)
        wm, wc = rule.wm, rule.wc
        chol_P = safe_chol(P)
        X = quadrature.transform(rule, m, chol_P.factor, is_chol=True)
        Z = hv(X, t)
        z0 = wm @ Z
        z_hat = z0 + noise_mean
        missing, z = safe_z(z, z_hat)
        dZ = Z - z0
        S = gaussian.symmetrize(_weighted_cov(wc, dZ, dZ) + noise_cov)
        Pxz = _weighted_cov(wc, X - m, dZ)
        chol_S = safe_chol(S)
        K = kalman_gain(Pxz, chol_S.factor)
        y = z - z_hat
        mean = m + K @ y
        cov, rep_post = repair_cov(P - K @ S @ K.T)
        ll = loglik_from_chol(y, chol_S.factor)
        info = finish_info(missing, ll, y, S, chol_P.repaired | chol_S.repaired | rep_post)
        return select_state(missing, state, GaussianState(mean, cov)), info

    return LocalFilter(gaussian_state_init, predict, update, gaussian_state_moments)


def local_ukf(f, h, alpha: float = 1.0, beta: float = 0.0, kappa: float | None = None) -> LocalFilter:
    """Unscented KF with the scaled UT (seed 002 eqs 27–32; defaults of :func:`quadrature.unscented`).

    FilterPy's ``MerweScaledSigmaPoints(d, alpha, beta, kappa)`` is the same point set.

    Args:
        f, h: transition and measurement functions ``(x, t) -> ...``.
        alpha, beta, kappa: scaled-UT parameters; ``kappa=None`` means ``3 - d``.

    Raises:
        ValueError: ``alpha <= 0`` or non-finite parameters (eagerly); ``d + lambda <= 0`` when
            the filter is first traced (the state dimension is known then).
    """
    quadrature.unscented(1, alpha, beta, 0.0 if kappa is None else max(float(kappa), 0.0))
    return local_sigma(
        f, h, lambda d, dtype: quadrature.unscented(d, alpha, beta, kappa, dtype=dtype)
    )


def local_ckf(f, h) -> LocalFilter:
    """Cubature KF: third-degree spherical-radial rule, ``2d`` points (seed 001 eq 7)."""
    return local_sigma(f, h, lambda d, dtype: quadrature.cubature(d, dtype=dtype))


def local_ghkf(f, h, order: int = 3) -> LocalFilter:
    """Gauss–Hermite KF: tensor rule with ``order^d`` points (seed 002 eqs 35–38)."""
    quadrature.gauss_hermite(1, order)  # validate eagerly
    return local_sigma(f, h, lambda d, dtype: quadrature.gauss_hermite(d, order, dtype=dtype))


def local_sgkf(f, h, level: int = 2, growth: str = "linear") -> LocalFilter:
    """Sparse-grid (Smolyak Gauss–Hermite) quadrature KF (seed 002 §II-C)."""
    quadrature.smolyak(1, level, growth)  # validate eagerly
    return local_sigma(
        f, h, lambda d, dtype: quadrature.smolyak(d, level, growth, dtype=dtype)
    )


# ---------------------------------------------------------------------------------------------
# Square-root cubature Kalman filter (seed 001 eqs 8–22).


def tria(A: jax.Array) -> jax.Array:
    """``Tria(A)``: lower-triangular ``S`` with ``S S^T = A A^T`` (seed 001 eq 11), via QR of ``A^T``.

    The columns are sign-normalised so the diagonal is non-negative.

    Args:
        A: ``(d, k)`` with ``k >= d``.
    """
    R = jnp.linalg.qr(A.T, mode="r")  # (d, d) upper, A^T = Q R  =>  A A^T = R^T R
    S = R.T
    sign = jnp.where(jnp.diagonal(S) < 0, -1.0, 1.0).astype(S.dtype)
    return S * sign[None, :]


def _sqrt_init(mean, cov) -> SqrtState:
    mean = jnp.asarray(mean)
    return SqrtState(mean, safe_chol(jnp.asarray(cov, mean.dtype)).factor)


def _sqrt_moments(state: SqrtState):
    return state.mean, state.chol @ state.chol.T


def _fix_factor(S):
    """Replace a singular factor (a zero on the diagonal) by a repaired one; flag it."""
    diag = jnp.abs(jnp.diagonal(S))
    bad = jnp.any(diag <= jnp.finfo(S.dtype).tiny) | ~jnp.all(jnp.isfinite(S))
    res = safe_chol(jnp.where(bad, S @ S.T, jnp.eye(S.shape[0], dtype=S.dtype)))
    return jnp.where(bad, res.factor, S), bad


def local_sckf(f, h) -> LocalFilter:
    """Square-root cubature Kalman filter (seed 001 eqs 8–22).

    State: :class:`SqrtState` ``(mean, chol)``. Predict (eqs 8–12):
    ``X_i = S xi_i + m``, ``X*_i = f(X_i)``, ``m' = (1/2d) sum X*_i + q_mean``,
    ``S' = Tria([chi*, S_Q])`` with ``chi* = [X*_i - m'_0] / sqrt(2d)``. Update (eqs 13–22):
    ``X_i = S' xi_i + m'``, ``Z_i = h(X_i)``, ``z_hat = mean(Z) + r_mean``,
    ``S_zz = Tria([Zc, S_R])``, ``Pxz = chi Zc^T``, ``W = (Pxz / S_zz^T) / S_zz``,
    ``m+ = m' + W (z - z_hat)``, ``S+ = Tria([chi - W Zc, W S_R])``.

    ``S_Q``, ``S_R`` are Cholesky factors of the noise covariances (repaired if needed; the
    update flags a repaired ``R`` or a singular factor).
    """
    fv = jax.vmap(f, in_axes=(0, None))
    hv = jax.vmap(h, in_axes=(0, None))
    get_rule = _rule_getter(lambda d, dtype: quadrature.cubature(d, dtype=dtype))

    def _rule_and_scale(m):
        rule = get_rule(m.shape[-1], m.dtype)
        return rule, 1.0 / math.sqrt(rule.num_points)

    def predict(state: SqrtState, t, noise_mean, noise_cov) -> SqrtState:
        rule, scale = _rule_and_scale(state.mean)
        X = quadrature.transform(rule, state.mean, state.chol, is_chol=True)  # eq 8
        Y = fv(X, t)  # eq 9
        mean0 = jnp.mean(Y, axis=0)  # eq 10
        chi = (Y - mean0).T * scale  # eq 12
        S_Q = safe_chol(noise_cov).factor
        S, _ = _fix_factor(tria(jnp.concatenate([chi, S_Q], axis=1)))  # eq 11
        return SqrtState(mean0 + noise_mean, S)

    def update(state: SqrtState, z, t, noise_mean, noise_cov):
        m, S = state
        rule, scale = _rule_and_scale(m)
        X = quadrature.transform(rule, m, S, is_chol=True)  # eq 13
        Zp = hv(X, t)  # eq 14
        z0 = jnp.mean(Zp, axis=0)  # eq 15
        z_hat = z0 + noise_mean
        missing, z = safe_z(z, z_hat)
        Zc = (Zp - z0).T * scale  # eq 17
        chol_R = safe_chol(noise_cov)
        S_R = chol_R.factor
        S_zz, bad_zz = _fix_factor(tria(jnp.concatenate([Zc, S_R], axis=1)))  # eq 16
        chi = (X - m).T * scale  # eq 19
        Pxz = chi @ Zc.T  # eq 18
        # eq 20: W = (Pxz / S_zz^T) / S_zz, i.e. W = Pxz (S_zz S_zz^T)^{-1}
        W = solve_triangular(
            S_zz.T, solve_triangular(S_zz, Pxz.T, lower=True), lower=False
        ).T
        y = z - z_hat
        mean = m + W @ y  # eq 21
        S_new, bad_post = _fix_factor(
            tria(jnp.concatenate([chi - W @ Zc, W @ S_R], axis=1))
        )  # eq 22
        ll = loglik_from_chol(y, S_zz)
        info = finish_info(
            missing, ll, y, S_zz @ S_zz.T, chol_R.repaired | bad_zz | bad_post
        )
        return select_state(missing, state, SqrtState(mean, S_new)), info

    return LocalFilter(_sqrt_init, predict, update, _sqrt_moments)


# ---------------------------------------------------------------------------------------------
# Model-level builders.


def build_sigma(model: StateSpaceModel, rule: SigmaPoints) -> Filter:
    """Model-level sigma-point filter with any rule (GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    rule = _check_rule(rule)
    if rule.dim != d:
        raise ValueError(f"rule: dimension {rule.dim} does not match the state dimension {d}")
    return from_local(model, local_sigma(model.f, model.h, rule))


def build_ukf(
    model: StateSpaceModel, alpha: float = 1.0, beta: float = 0.0, kappa: float | None = None
) -> Filter:
    """Model-level UKF (scaled UT; GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    quadrature.unscented(d, alpha, beta, kappa)  # validate eagerly
    return from_local(model, local_ukf(model.f, model.h, alpha, beta, kappa))


def build_ckf(model: StateSpaceModel) -> Filter:
    """Model-level cubature KF (GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    return from_local(model, local_ckf(model.f, model.h))


def build_ghkf(model: StateSpaceModel, order: int = 3) -> Filter:
    """Model-level Gauss–Hermite KF (GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    return from_local(model, local_ghkf(model.f, model.h, order))


def build_sgkf(model: StateSpaceModel, level: int = 2, growth: str = "linear") -> Filter:
    """Model-level sparse-grid quadrature KF (GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    return from_local(model, local_sgkf(model.f, model.h, level, growth))


def build_sckf(model: StateSpaceModel) -> Filter:
    """Model-level square-root cubature KF (GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    return from_local(model, local_sckf(model.f, model.h))
