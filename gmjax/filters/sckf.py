"""Square-root cubature Kalman filter (seed 001 eqs 8–22).

:func:`local_sckf` carries the lower Cholesky factor ``S`` (:class:`SqrtState`) and re-triangularises with a QR decomposition
(``Tria``), never forming a covariance.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from gmjax import gaussian, quadrature
from gmjax._types import StepFn
from gmjax.filters._core import (
    LocalFilter,
    SqrtState,
    check_model,
    circular_mean,
    finish_info,
    from_local,
    loglik_from_chol,
    safe_chol,
    safe_z,
    select_state,
    wrap_angles,
)
from gmjax.filters._sigma import rule_getter
from gmjax.filters.base import Filter
from gmjax.models.base import StateSpaceModel, as_step_fn

__all__ = ["local_sckf", "build_sckf", "tria"]


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


def local_sckf(f: StepFn, h: StepFn, angle_dims: tuple[int, ...] = ()) -> LocalFilter:
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
    angle_dims = tuple(angle_dims)  # angular measurement components: circular mean, wrapped residuals
    fv = jax.vmap(as_step_fn(f), in_axes=(0, None))
    hv = jax.vmap(as_step_fn(h), in_axes=(0, None))
    get_rule = rule_getter(lambda d, dtype: quadrature.cubature(d, dtype=dtype))

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
        z0 = circular_mean(Zp, jnp.full(Zp.shape[0], 1.0 / Zp.shape[0], Zp.dtype), angle_dims)  # eq 15
        z_hat = z0 + noise_mean
        missing, z = safe_z(z, z_hat)
        Zc = wrap_angles(Zp - z0, angle_dims).T * scale  # eq 17
        chol_R = safe_chol(noise_cov)
        S_R = chol_R.factor
        S_zz, bad_zz = _fix_factor(tria(jnp.concatenate([Zc, S_R], axis=1)))  # eq 16
        chi = (X - m).T * scale  # eq 19
        Pxz = chi @ Zc.T  # eq 18
        # eq 20: W = (Pxz / S_zz^T) / S_zz, i.e. W = Pxz (S_zz S_zz^T)^{-1}
        W = gaussian.cho_solve_small(S_zz, Pxz.T).T
        y = wrap_angles(z - z_hat, angle_dims)
        mean = m + W @ y  # eq 21
        S_new, bad_post = _fix_factor(tria(jnp.concatenate([chi - W @ Zc, W @ S_R], axis=1)))  # eq 22
        ll = loglik_from_chol(y, S_zz)
        info = finish_info(missing, ll, y, S_zz @ S_zz.T, chol_R.repaired | bad_zz | bad_post)
        return select_state(missing, state, SqrtState(mean, S_new)), info

    return LocalFilter(_sqrt_init, predict, update, _sqrt_moments)


def build_sckf(model: StateSpaceModel) -> Filter:
    """Model-level square-root cubature KF (GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    f, h, _, _ = model.step_fns()
    return from_local(model, local_sckf(f, h, model.angle_dims))
