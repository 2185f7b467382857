"""Plain NumPy/SciPy references for a scalar model with Gaussian-mixture measurement noise (no JAX).

The model is ``x_k = a x_{k-1} + w_k`` (``w ~ N(0, q)``), ``z_k = x_k + v_k`` with ``v`` a 1-D
Gaussian mixture (weights ``w_j``, means ``mu_j``, variances ``s2_j``), ``x_0 ~ N(m0, p0)``,
measured at ``k = 1..T`` (``x_0`` is the prior, ``z_1`` measures ``x_1``).

* :func:`grid_loglik` - ``log p(z_1..z_T)`` by a point-mass filter on a uniform grid.
* :func:`em_iid` - EM for a 1-D mixture fitted to i.i.d. samples (the known-state limit).
* :func:`ml_fit_grid` - maximum-likelihood mixture parameters of :func:`grid_loglik`.

Grid discretisation (:func:`transition_matrix`): the state is carried as density values ``d_i``
on the grid, ``sum_i d_i dx ~ 1``. A Gaussian whose standard deviation is at least the spacing
``dx`` is evaluated pointwise; the Riemann sums of smooth Gaussians on a uniform grid converge
spectrally (error ~ ``exp(-2 pi^2 sigma^2 / dx^2)``), so the log-likelihood is exact to rounding once
``dx`` resolves every width involved (``sqrt(q) / max(|a|, 1)``, the mixture's ``sqrt(s2_j)`` and
the posterior's width) and the grid covers the trajectory with margin. A narrower Gaussian (tiny
``q`` or ``p0``) is replaced by its *cell average* (differences of the normal CDF over the cells
``[x_i - dx/2, x_i + dx/2]``): in the limit ``q, p0 -> 0`` it puts all mass in the cell of the
deterministic state, which is exact when that state is a grid point (``a = 1`` and ``m0`` on the
grid); in between (``sqrt(q)`` near ``dx``) it is a rough ``O(dx^2)`` approximation only.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.optimize import minimize
from scipy.special import logsumexp, ndtr

from references.kalman_np import central_gradient

_LOG_2PI = float(np.log(2.0 * np.pi))


def gm_logpdf(x, weights, means, variances):
    """Log-density of a 1-D Gaussian mixture at ``x`` (any shape), by log-sum-exp."""
    x = np.asarray(x, float)[..., None]
    w, m, v = (np.atleast_1d(np.asarray(a, float)) for a in (weights, means, variances))
    comp = np.log(w) - 0.5 * (x - m) ** 2 / v - 0.5 * np.log(v) - 0.5 * _LOG_2PI
    return logsumexp(comp, axis=-1)


def _gauss_density(diff, var, dx, pointwise):
    """Density of ``N(0, var)`` at ``diff`` (any shape): pointwise, or averaged over the cell
    ``[diff - dx/2, diff + dx/2]`` (``Phi`` differences, accurate in both tails)."""
    if pointwise:
        return np.exp(-0.5 * diff * diff / var) / np.sqrt(2 * np.pi * var)
    sd = np.sqrt(var)
    if sd == 0.0:
        return (np.abs(diff) <= 0.5 * dx) / dx
    hi, lo = (diff + 0.5 * dx) / sd, (diff - 0.5 * dx) / sd
    mass = np.where(lo > 0, ndtr(-lo) - ndtr(-hi), ndtr(hi) - ndtr(lo))
    return np.maximum(mass, 0.0) / dx


def _spacing(grid):
    grid = np.asarray(grid, float)
    dx = grid[1] - grid[0]
    if not np.allclose(np.diff(grid), dx, rtol=1e-9, atol=0.0):
        raise ValueError("grid must be uniformly spaced and increasing")
    return grid, float(dx)


def transition_matrix(grid, a, q):
    """``(G, G)`` ``K[i, j] ~ p(x_k = grid[i] | x_{k-1} = grid[j])`` (a density in ``i``).

    Pointwise ``N(grid[i]; a grid[j], q)`` when ``sqrt(q) / max(|a|, 1) >= dx``, else cell-averaged
    (see the module docstring). Columns are not renormalised: mass leaving the grid is lost, so a
    grid that does not cover the trajectory shows up as a too-low likelihood.
    """
    grid, dx = _spacing(grid)
    pointwise = np.sqrt(q) / max(abs(a), 1.0) >= dx
    return _gauss_density(grid[:, None] - a * grid[None, :], q, dx, pointwise)


def first_prediction(grid, a, q, m0, p0):
    """``(G,)`` density of ``x_1 ~ N(a m0, a^2 p0 + q)`` on ``grid`` (exact Gaussian, so ``p0``
    need not be resolved by the grid; cell-averaged when its std is below ``dx``)."""
    grid, dx = _spacing(grid)
    var = a * a * p0 + q
    return _gauss_density(grid - a * m0, var, dx, np.sqrt(var) >= dx)


def _grid_loglik(zs, K, pred1, grid, dx, weights, means, variances, check=True):
    """Point-mass filter with a precomputed transition matrix ``K (G, G)`` and ``pred1 (G,)``.

    With ``check``, warns (``RuntimeWarning``) when a filtered density puts more than ``1e-10`` of
    its mass in the two outermost cells: the grid then does not cover the trajectory.
    """
    zs = np.asarray(zs, float).reshape(-1)
    loglike = gm_logpdf(zs[:, None] - grid[None, :], weights, means, variances)  # (T, G)
    top = loglike.max(axis=1, keepdims=True)
    like = np.exp(loglike - top)  # scaled, so a far-off z_k does not underflow
    ll, post, edge = 0.0, None, 0.0
    for k in range(len(zs)):
        pred = pred1 if k == 0 else (K @ post) * dx
        if np.isnan(zs[k]):
            post = pred
            continue
        unnorm = pred * like[k]
        c = unnorm.sum() * dx  # p(z_k | z_1..k-1) / exp(top_k)
        ll += np.log(c) + top[k, 0]
        post = unnorm / c
        edge = max(edge, (post[0] + post[-1]) * dx)
    if check and edge > 1e-10:
        warnings.warn(
            f"grid_loglik: filtered mass {edge:.1e} at the grid's ends; widen the grid",
            RuntimeWarning,
            stacklevel=3,
        )
    return float(ll)


def grid_loglik(zs, a, q, weights, means, variances, m0, p0, grid) -> float:
    """``log p(z_1..z_T)`` of the scalar model with mixture measurement noise, on a grid.

    Predict (``x_1``: the exact Gaussian :func:`first_prediction`; later steps: the transition
    density matrix, a Riemann sum with spacing ``dx``), multiply by the mixture likelihood
    ``p(z_k | x) = sum_j w_j N(z_k - x; mu_j, s2_j)``, normalise; the log normalisers (densities,
    the ``dx`` of each Riemann sum included) add up to the log-likelihood.

    Args:
        zs: ``(T,)`` measurements (NaN: predict-only step, adds 0).
        a, q: transition coefficient and process-noise variance.
        weights, means, variances: ``(n,)`` measurement-noise mixture.
        m0, p0: prior mean and variance of ``x_0``.
        grid: ``(G,)`` uniformly spaced points covering the state trajectory with margin
            (the caller's job, see the module docstring for the spacing needed; a
            ``RuntimeWarning`` says when a filtered density reaches the grid's ends). Cost
            ``O(G^2)`` memory and ``O(T G^2)`` time.

    Returns:
        The log-likelihood (float).
    """
    grid, dx = _spacing(grid)
    K = transition_matrix(grid, a, q)
    pred1 = first_prediction(grid, a, q, m0, p0)
    return _grid_loglik(zs, K, pred1, grid, dx, weights, means, variances)


def em_iid(samples, weights0, means0, variances0, iters=500, tol=1e-12):
    """EM for a 1-D Gaussian mixture fitted to i.i.d. ``samples (N,)``.

    Stops when one iteration changes every parameter by at most ``tol`` (weights absolutely,
    means relative to their component's standard deviation, variances relatively), or after
    ``iters`` iterations with a ``RuntimeWarning``. A parameter criterion, not a log-likelihood one:
    EM converges linearly, so a tiny log-likelihood increment can still leave the parameters ~1e-5
    off, while the EM map's fixed point is computed without cancellation and reached to ~1e-12.

    Returns:
        ``(weights (n,), means (n,), variances (n,), loglik)``: the final parameters and the total
        log-likelihood ``sum_i log p(samples_i)`` at them.
    """
    x = np.asarray(samples, float).reshape(-1)[:, None]
    w, m, v = (np.array(np.atleast_1d(a), float) for a in (weights0, means0, variances0))
    change = np.inf
    for _ in range(iters):
        logc = np.log(w) - 0.5 * (x - m) ** 2 / v - 0.5 * np.log(v) - 0.5 * _LOG_2PI  # (N, n)
        resp = np.exp(logc - logsumexp(logc, axis=1, keepdims=True))
        nk = resp.sum(axis=0)
        w_new = nk / nk.sum()
        m_new = (resp * x).sum(axis=0) / nk
        v_new = (resp * (x - m_new) ** 2).sum(axis=0) / nk
        change = max(
            np.abs(w_new - w).max(), (np.abs(m_new - m) / np.sqrt(v)).max(), (np.abs(v_new - v) / v).max()
        )
        w, m, v = w_new, m_new, v_new
        if change <= tol:
            break
    else:
        warnings.warn(
            f"em_iid: not converged in {iters} iterations (last change {change:.2e})",
            RuntimeWarning,
            stacklevel=2,
        )
    ll = float(gm_logpdf(x[:, 0], w, m, v).sum())
    return w, m, v, ll


def _unpack(theta, n):
    """``theta = (log(w_j / w_n) for j < n, mu_1..mu_n, log s2_1..log s2_n)`` -> ``(w, mu, s2)``."""
    logits = np.concatenate([theta[: n - 1], [0.0]])
    w = np.exp(logits - logsumexp(logits))
    return w, np.asarray(theta[n - 1 : 2 * n - 1]), np.exp(theta[2 * n - 1 :])


def ml_fit_grid(zs, a, q, m0, p0, grid, weights0, means0, variances0) -> dict:
    """Maximum-likelihood measurement-noise mixture of :func:`grid_loglik` (``a, q, m0, p0`` fixed).

    Parameters ``theta = (log(w_1/w_n), .., log(w_{n-1}/w_n), mu_1..mu_n, log s2_1..log s2_n)``
    (for ``n = 2``: logit of ``w_1``, ``mu_1``, ``mu_2``, ``log s2_1``, ``log s2_2``), started at
    ``(weights0, means0, variances0)``; a loose Nelder-Mead (``xatol=1e-4``), then BFGS
    (``gtol=1e-8``) with a 5-point central-difference gradient (step ``1e-3`` in ``theta``).
    The transition matrix and the first prediction are built once; each evaluation costs
    ``O(T G^2)``, a fit some 1000-2000 evaluations.

    Returns:
        dict with ``weights``, ``means``, ``variances`` (``(n,)``, components sorted by mean),
        ``loglik``, ``theta`` (unsorted), ``grad`` (central-difference gradient of the
        log-likelihood w.r.t. ``theta`` at the optimum), ``result`` (BFGS) and ``nelder_mead``.
    """
    grid, dx = _spacing(grid)
    K = transition_matrix(grid, a, q)
    pred1 = first_prediction(grid, a, q, m0, p0)
    zs = np.asarray(zs, float).reshape(-1)
    w0 = np.asarray(weights0, float)
    n = len(w0)

    def negll(theta):
        w, mu, s2 = _unpack(theta, n)
        return -_grid_loglik(zs, K, pred1, grid, dx, w, mu, s2, check=False)

    def jac(theta):
        return central_gradient(negll, theta)

    theta0 = np.concatenate(
        [np.log(w0[:-1] / w0[-1]), np.asarray(means0, float), np.log(np.asarray(variances0, float))]
    )
    nm = minimize(
        negll,
        theta0,
        method="Nelder-Mead",
        options={"xatol": 1e-4, "fatol": 1e-8, "maxiter": 20000, "maxfev": 20000, "adaptive": True},
    )
    res = minimize(negll, nm.x, jac=jac, method="BFGS", options={"gtol": 1e-8, "maxiter": 500})
    theta = res.x if res.fun <= nm.fun else nm.x
    w, mu, s2 = _unpack(theta, n)
    loglik = _grid_loglik(zs, K, pred1, grid, dx, w, mu, s2)  # warns if the grid is too narrow
    order = np.argsort(mu, kind="stable")
    return {
        "weights": w[order],
        "means": mu[order],
        "variances": s2[order],
        "loglik": loglik,
        "theta": theta,
        "grad": -jac(theta),
        "result": res,
        "nelder_mead": nm,
    }
