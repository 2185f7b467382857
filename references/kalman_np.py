"""Plain NumPy/SciPy Kalman-filter log-likelihood and its maximum-likelihood noise fit (no JAX).

The linear-Gaussian model is ``x_k = F x_{k-1} + w_k`` (``w ~ N(0, Q)``), ``z_k = H x_k + v_k``
(``v ~ N(0, R)``), ``x_0 ~ N(m0, P0)``, measured at ``k = 1..T`` (predict first, then update, as
gmjax's filters do: ``x_0`` is the prior and ``z_1`` measures ``x_1``).

* :func:`kalman_loglik` - exact ``log p(z_1..z_T)`` by the prediction-error decomposition.
* :func:`kalman_loglik_batch` - its sum over a batch of independent sequences
  (:func:`kalman_logliks`: the per-sequence values, vectorised over the batch).
* :func:`ml_noise_variances` - maximum-likelihood scalars ``q, r`` of ``Q = q Q_shape``,
  ``R = r R_shape`` (Nelder-Mead, then BFGS on a 5-point central-difference gradient and a
  Newton polish).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

_LOG_2PI = float(np.log(2.0 * np.pi))


def kalman_logliks(zs_batch, F, H, Q, R, m0, P0) -> np.ndarray:
    """Per-sequence :func:`kalman_loglik` of ``zs_batch (B, T, m)``, vectorised over the batch.

    Returns:
        ``(B,)`` log-likelihoods.
    """
    zs = np.asarray(zs_batch, float)
    if zs.ndim == 2:  # (B, T) scalar measurements
        zs = zs[..., None]
    F, H, Q, R, P0 = (np.atleast_2d(np.asarray(a, float)) for a in (F, H, Q, R, P0))
    B, _, dim_z = zs.shape
    d = F.shape[0]
    m = np.broadcast_to(np.atleast_1d(np.asarray(m0, float)), (B, d)).copy()
    P = np.broadcast_to(P0, (B, d, d)).copy()
    eye = np.eye(d)
    ll = np.zeros(B)
    for zk in np.moveaxis(zs, 1, 0):  # (B, m)
        m = m @ F.T
        P = F @ P @ F.T + Q
        obs = ~np.isnan(zk).any(axis=-1)
        if not obs.any():
            continue
        e = np.where(obs[:, None], zk, 0.0) - m @ H.T  # (B, m)
        S = H @ P @ H.T + R
        S = 0.5 * (S + np.swapaxes(S, -1, -2))
        L = np.linalg.cholesky(S)
        u = np.linalg.solve(L, e[..., None])[..., 0]
        llk = -0.5 * np.sum(u * u, -1) - np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)
        ll += np.where(obs, llk - 0.5 * dim_z * _LOG_2PI, 0.0)
        K = np.swapaxes(np.linalg.solve(S, H @ P), -1, -2)  # P H' S^-1 (P, S symmetric), (B, d, m)
        A = eye - K @ H
        Pn = A @ P @ np.swapaxes(A, -1, -2) + K @ R @ np.swapaxes(K, -1, -2)  # Joseph form
        m = np.where(obs[:, None], m + (K @ e[..., None])[..., 0], m)
        P = np.where(obs[:, None, None], 0.5 * (Pn + np.swapaxes(Pn, -1, -2)), P)
    return ll


def kalman_loglik(zs, F, H, Q, R, m0, P0) -> float:
    """Exact ``log p(z_1..z_T)`` of the linear-Gaussian model.

    Args:
        zs: ``(T, m)`` measurements (``(T,)`` is read as ``m = 1``); a row containing any NaN is
            a predict-only step (adds 0).
        F: ``(d, d)``. H: ``(m, d)``. Q: ``(d, d)``. R: ``(m, m)``.
        m0: ``(d,)`` prior mean of ``x_0``. P0: ``(d, d)`` its covariance.

    Returns:
        The log-likelihood (float), the sum of ``log N(z_k; H m_k|k-1, H P_k|k-1 H' + R)``.
    """
    zs = np.asarray(zs, float)
    zs = zs[:, None] if zs.ndim == 1 else zs
    return float(kalman_logliks(zs[None], F, H, Q, R, m0, P0)[0])


def kalman_loglik_batch(zs_batch, F, H, Q, R, m0, P0) -> float:
    """Sum of :func:`kalman_loglik` over ``zs_batch (B, T, m)`` (independent sequences)."""
    return float(kalman_logliks(zs_batch, F, H, Q, R, m0, P0).sum())


def central_gradient(fun, x, h=1e-3):
    """5-point central-difference gradient of scalar ``fun`` at ``x (n,)`` (error ``O(h^4)``)."""
    x = np.asarray(x, float)
    g = np.empty_like(x)
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        g[i] = (-fun(x + 2 * e) + 8 * fun(x + e) - 8 * fun(x - e) + fun(x - 2 * e)) / (12 * h)
    return g


def ml_noise_variances(zs_batch, F, H, m0, P0, q0, r0, Q_shape, R_shape):
    """Maximum-likelihood ``q, r`` of ``Q = q Q_shape``, ``R = r R_shape`` over a batch.

    Minimises the negative batch log-likelihood over ``theta = (log q, log r)``: Nelder-Mead from
    ``(log q0, log r0)``, then BFGS with a 5-point central-difference gradient (step ``1e-3`` in
    ``theta``, error ~1e-10 for log-likelihoods of order 1e3) and ``gtol=1e-10``, then up to five
    Newton steps (finite-difference Hessian) while they shrink the gradient, until ``|g| < 1e-9``.

    Args:
        zs_batch: ``(B, T, m)`` measurements (NaN rows: predict-only).
        F, H, m0, P0: as in :func:`kalman_loglik`. q0, r0: positive starting values.
        Q_shape: ``(d, d)``. R_shape: ``(m, m)``.

    Returns:
        ``(q, r, result)``: floats and the BFGS ``OptimizeResult`` (``x``, ``fun`` updated to the
        polished point; ``message`` is BFGS's own, often "precision loss"); ``result.grad_theta`` is the
        central-difference gradient of the batch *log-likelihood* w.r.t. ``(log q, log r)`` at the
        returned point, ``result.loglik`` its value and ``result.nelder_mead`` the first stage.
    """
    zs_batch = np.asarray(zs_batch, float)
    Q_shape = np.atleast_2d(np.asarray(Q_shape, float))
    R_shape = np.atleast_2d(np.asarray(R_shape, float))

    def negll(theta):
        q, r = np.exp(theta)
        return -kalman_loglik_batch(zs_batch, F, H, q * Q_shape, r * R_shape, m0, P0)

    def jac(theta):
        return central_gradient(negll, theta)

    x0 = np.log([float(q0), float(r0)])
    nm = minimize(negll, x0, method="Nelder-Mead", options={"xatol": 1e-9, "fatol": 1e-12, "maxiter": 5000})
    res = minimize(negll, nm.x, jac=jac, method="BFGS", options={"gtol": 1e-10, "maxiter": 200})
    # BFGS may stop early on "precision loss" near the optimum; finish with a few Newton steps.
    theta, g = res.x, jac(res.x)
    for _ in range(5):
        if np.max(np.abs(g)) < 1e-9:
            break
        Hm = np.array([central_gradient(lambda t, i=i: jac(t)[i], theta) for i in range(2)])
        step = np.linalg.solve(0.5 * (Hm + Hm.T), g)
        theta_new = theta - step
        g_new = jac(theta_new)
        if np.max(np.abs(g_new)) >= np.max(np.abs(g)):
            break
        theta, g = theta_new, g_new
    q, r = np.exp(theta)
    res.x = theta
    res.grad_theta = -g
    res.fun = negll(theta)
    res.loglik = -res.fun
    res.nelder_mead = nm
    return float(q), float(r), res
