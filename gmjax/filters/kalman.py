"""Kalman filter (linear / affine models) and extended Kalman filter.

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
    Filter,
    GaussianState,
    LocalFilter,
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

__all__ = ["local_kf", "local_ekf", "build_kf", "build_ekf"]

Linearize = Callable[[jax.Array, jax.Array], tuple[jax.Array, jax.Array]]


def _linearized_filter(f_lin: Linearize, h_lin: Linearize) -> LocalFilter:
    """A local filter from ``f_lin(m, t) -> (f(m, t), F)`` and ``h_lin(m, t) -> (h(m, t), H)``."""

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
        y = z - z_hat
        mean = m + K @ y
        A = jnp.eye(m.shape[0], dtype=P.dtype) - K @ H
        cov, rep_post = repair_cov(A @ P @ A.T + K @ noise_cov @ K.T)
        ll = loglik_from_chol(y, chol_S.factor)
        new = GaussianState(mean, cov)
        info = finish_info(missing, ll, y, S, chol_S.repaired | rep_post)
        return select_state(missing, state, new), info

    return LocalFilter(gaussian_state_init, predict, update, gaussian_state_moments)


def _as_time_fn(name: str, M) -> Callable:
    if callable(M):
        return M
    arr = jnp.asarray(M)
    if arr.ndim != 2:
        raise ValueError(f"{name}: expected a 2-D matrix or a callable t -> matrix, got shape {arr.shape}")
    if not isinstance(arr, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(arr))):
        raise ValueError(f"{name}: contains NaN or inf")
    return lambda t: arr


def local_kf(F, H) -> LocalFilter:
    """Kalman filter for ``x' = F x + v``, ``z = H x + w`` (noise means allowed).

    Args:
        F: ``(d, d)`` transition matrix, or a callable ``t -> (d, d)``.
        H: ``(m, d)`` measurement matrix, or a callable ``t -> (m, d)``.

    Returns:
        A :class:`LocalFilter` over :class:`GaussianState`.

    Raises:
        ValueError: non-square ``F``, ``H`` whose column count differs from ``F``'s size, or
            non-finite entries.
    """
    Ff = _as_time_fn("F", F)
    Hf = _as_time_fn("H", H)
    if not callable(F) and not callable(H):
        Fa, Ha = np.shape(F), np.shape(H)
        if Fa[0] != Fa[1]:
            raise ValueError(f"F: must be square (d, d), got {Fa}")
        if Ha[1] != Fa[0]:
            raise ValueError(f"H: expected shape (m, {Fa[0]}) to match F, got {Ha}")

    def f_lin(m, t):
        Fm = Ff(t).astype(m.dtype)
        return Fm @ m, Fm

    def h_lin(m, t):
        Hm = Hf(t).astype(m.dtype)
        return Hm @ m, Hm

    return _linearized_filter(f_lin, h_lin)


def _with_jacobian(fn, jac) -> Linearize:
    jac = jax.jacfwd(fn) if jac is None else jac

    def lin(m, t):
        return fn(m, t), jac(m, t)

    return lin


def local_ekf(f, h, f_jacobian=None, h_jacobian=None) -> LocalFilter:
    """Extended Kalman filter (first-order linearisation at the mean; seed 000 eqs 3–18 per component).

    Args:
        f: ``f(x (d,), t) -> (d,)``.
        h: ``h(x (d,), t) -> (m,)``.
        f_jacobian, h_jacobian: optional ``(x, t) -> (d, d)`` / ``(m, d)``; default
            ``jax.jacfwd`` of ``f`` / ``h`` in ``x``.

    Returns:
        A :class:`LocalFilter` over :class:`GaussianState`.
    """
    return _linearized_filter(_with_jacobian(f, f_jacobian), _with_jacobian(h, h_jacobian))


def _affine_parts(fn):
    """``x -> (fn(x), J)`` for an affine ``fn``: the Jacobian at 0 and the value at ``x``."""

    def lin(m, t):
        J = jax.jacfwd(fn)(jnp.zeros_like(m), t)
        return fn(m, t), J

    return lin


def build_kf(model: StateSpaceModel) -> Filter:
    """Kalman filter for an affine model (``f``, ``h`` affine in ``x``), model level.

    ``F_t`` and ``H_t`` are the Jacobians of ``f(., t)`` and ``h(., t)`` (exact for affine maps);
    the offsets come from evaluating ``f`` and ``h`` themselves. GM noises and a GM prior are
    moment-matched (see :func:`gmjax.filters.from_local`). For a non-affine model use
    :func:`build_ekf` (this filter would then be an EKF linearised at 0, which is wrong).
    """
    check_model(model)
    return from_local(model, _linearized_filter(_affine_parts(model.f), _affine_parts(model.h)))


def build_ekf(model: StateSpaceModel) -> Filter:
    """Extended Kalman filter for a model (Jacobians from the model or ``jax.jacfwd``).

    GM noises and a GM prior are moment-matched (see :func:`gmjax.filters.from_local`).
    """
    check_model(model)
    return from_local(
        model, local_ekf(model.f, model.h, model.f_jacobian, model.h_jacobian)
    )

