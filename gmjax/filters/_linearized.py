"""The linearised Kalman core shared by the KF and the EKF (engine, not an algorithm).

Both share one linearised core: predict ``m' = f(m, t) + q_mean``, ``P' = F P F^T + Q``;
update ``z_hat = h(m, t) + r_mean``, ``S = H P H^T + R``, ``K = P H^T S^{-1}``,
``m+ = m + K (z - z_hat)`` and the Joseph form ``P+ = (I - K H) P (I - K H)^T + K R K^T``
(FilterPy's ``KalmanFilter`` / ``ExtendedKalmanFilter`` update). For the KF, ``F`` and ``H`` are
given; for the EKF they are the Jacobians at the current mean (``jax.jacfwd`` unless supplied).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import gaussian
from gmjax.filters._core import (
    GaussianState,
    LocalFilter,
    finish_info,
    gaussian_state_init,
    gaussian_state_moments,
    kalman_gain,
    loglik_from_chol,
    repair_cov,
    safe_chol,
    safe_z,
    select_state,
    wrap_angles,
)

__all__ = ["Linearize", "linearized_filter", "as_time_fn", "with_jacobian", "affine_parts"]


Linearize = Callable[[jax.Array, jax.Array], tuple[jax.Array, jax.Array]]


def linearized_filter(f_lin: Linearize, h_lin: Linearize, angle_dims: tuple[int, ...] = ()) -> LocalFilter:
    """A local filter from ``f_lin(m, t) -> (f(m, t), F)`` and ``h_lin(m, t) -> (h(m, t), H)``.

    ``angle_dims``: measurement components that are angles; their innovations are wrapped into
    ``[-pi, pi)``.
    """

    def predict(state: GaussianState, t, noise_mean, noise_cov) -> GaussianState:
        fm, F = f_lin(state.mean, t)
        mean = fm + noise_mean
        cov = gaussian.symmetrize(F @ state.cov @ F.T + noise_cov)
        return GaussianState(mean, cov)

    def update(state: GaussianState, z, t, noise_mean, noise_cov):
        m, P = state
        hm, H = h_lin(m, t)
        z_hat = hm + noise_mean
        missing, z = safe_z(z, z_hat)
        S = gaussian.symmetrize(H @ P @ H.T + noise_cov)
        chol_S = safe_chol(S)
        K = kalman_gain(P @ H.T, chol_S.factor)
        y = wrap_angles(z - z_hat, angle_dims)
        mean = m + K @ y
        A = jnp.eye(m.shape[0], dtype=P.dtype) - K @ H
        cov, rep_post = repair_cov(A @ P @ A.T + K @ noise_cov @ K.T)
        ll = loglik_from_chol(y, chol_S.factor)
        new = GaussianState(mean, cov)
        info = finish_info(missing, ll, y, S, chol_S.repaired | rep_post)
        return select_state(missing, state, new), info

    return LocalFilter(gaussian_state_init, predict, update, gaussian_state_moments)


def as_time_fn(name: str, M) -> Callable:
    if callable(M):
        return M
    arr = jnp.asarray(M)
    if arr.ndim != 2:
        raise ValueError(f"{name}: expected a 2-D matrix or a callable t -> matrix, got shape {arr.shape}")
    if not isinstance(arr, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(arr))):
        raise ValueError(f"{name}: contains NaN or inf")
    return lambda t: arr


def with_jacobian(fn, jac) -> Linearize:
    jac = jax.jacfwd(fn) if jac is None else jac

    def lin(m, t):
        return fn(m, t), jac(m, t)

    return lin


def affine_parts(fn):
    """``x -> (fn(x), J)`` for an affine ``fn``: the Jacobian at 0 and the value at ``x``."""

    def lin(m, t):
        J = jax.jacfwd(fn)(jnp.zeros_like(m), t)
        return fn(m, t), J

    return lin
