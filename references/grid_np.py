"""Dense-grid (point-mass) references for scalar models, plain NumPy (no JAX).

* :func:`grid_filter_smoother` - Bayes filter and forward-backward smoother on a fixed grid for
  ``x_k = f(x_{k-1}) + v_k``, ``z_k = h(x_k) + w_k`` with arbitrary noise densities.
* :func:`gm_pdf`, :func:`gm_score_information` - a 1-D Gaussian mixture's density and the Fisher
  information ``E[(d/dw log p(w))^2]`` of its location, by dense trapezoidal integration.
"""

from __future__ import annotations

import numpy as np


def gm_pdf(x, weights, means, variances):
    """Density of a 1-D Gaussian mixture at ``x`` (any shape)."""
    x = np.asarray(x, float)[..., None]
    w, m, v = (np.asarray(a, float) for a in (weights, means, variances))
    return np.sum(w * np.exp(-0.5 * (x - m) ** 2 / v) / np.sqrt(2 * np.pi * v), axis=-1)


def gm_score_information(weights, means, variances, n_grid=400_001, width=40.0):
    """``I = int p'(w)^2 / p(w) dw`` of a 1-D Gaussian mixture (trapezoid on a dense grid)."""
    w, m, v = (np.asarray(a, float) for a in (weights, means, variances))
    s = np.sqrt(v.max())
    x = np.linspace(m.min() - width * s, m.max() + width * s, n_grid)
    comp = w * np.exp(-0.5 * (x[:, None] - m) ** 2 / v) / np.sqrt(2 * np.pi * v)
    p = comp.sum(axis=1)
    dp = np.sum(comp * (-(x[:, None] - m) / v), axis=1)
    integrand = np.where(p > 1e-300, dp * dp / np.maximum(p, 1e-300), 0.0)
    return np.trapezoid(integrand, x) if hasattr(np, "trapezoid") else np.trapz(integrand, x)


def grid_filter_smoother(grid, prior_pdf, f, h, process_pdf, measurement_pdf, zs):
    """Point-mass filter and forward-backward smoother on ``grid`` (uniform spacing).

    Args:
        grid: ``(G,)`` uniformly spaced points.
        prior_pdf: density of ``x_0`` (vectorised). f, h: vectorised maps.
        process_pdf, measurement_pdf: vectorised noise densities.
        zs: ``(T,)`` measurements (NaN: no measurement).

    Returns:
        ``(filtered, smoothed)``, each ``(T, G)`` normalised probability masses on the grid.
    """
    grid = np.asarray(grid, float)
    # K[i, j] = p(x_k = grid[i] | x_{k-1} = grid[j])
    K = process_pdf(grid[:, None] - f(grid)[None, :])
    K = K / np.maximum(K.sum(axis=0, keepdims=True), 1e-300)  # each column a probability vector
    p = prior_pdf(grid)
    p = p / p.sum()
    filtered, predicted = [], []
    for z in zs:
        pred = K @ p
        predicted.append(pred)
        like = np.ones_like(grid) if np.isnan(z) else measurement_pdf(z - h(grid))
        p = pred * like
        p = p / p.sum()
        filtered.append(p)
    filtered, predicted = np.stack(filtered), np.stack(predicted)
    smoothed = [filtered[-1]]
    for k in range(len(zs) - 2, -1, -1):
        ratio = np.where(predicted[k + 1] > 0, smoothed[0] / np.maximum(predicted[k + 1], 1e-300), 0.0)
        s = filtered[k] * (K.T @ ratio)
        smoothed.insert(0, s / s.sum())
    return filtered, np.stack(smoothed)


def grid_pcrb_1d(f, fprime, hprime, prior_pdf, process_pdf, info_w, info_v, grid, n_steps, J0):
    """PCRB of a scalar model ``x_{n+1} = f(x_n) + w``, ``z_n = h(x_n) + v`` on a dense grid.

    The state density ``p(x_n)`` is propagated on ``grid`` (point masses convolved with the process
    noise density, which may be a mixture), the expectations of seed 002 eqs 5-8 are grid sums with
    the noises' Fisher informations ``info_w``, ``info_v``, and eq 4 runs in float64.

    Returns:
        ``(T + 1,)`` bounds ``1 / J_n``.
    """
    grid = np.asarray(grid, float)
    dx = grid[1] - grid[0]
    Kmat = process_pdf(grid[:, None] - f(grid)[None, :]) * dx  # column j: density of x' given x_j
    p = prior_pdf(grid) * dx
    p = p / p.sum()
    J = float(J0)
    out = [1.0 / J]
    for _ in range(n_steps):
        Fx = fprime(grid)
        D11 = info_w * np.sum(p * Fx * Fx)
        D12 = -info_w * np.sum(p * Fx)
        p = Kmat @ p
        p = p / p.sum()
        Hx = hprime(grid)
        D22 = info_w + info_v * np.sum(p * Hx * Hx)
        J = D22 - D12 * D12 / (J + D11)
        out.append(1.0 / J)
    return np.asarray(out)
