"""Plain NumPy PCRB references written straight from seed 002 (no JAX).

* :func:`kalman_covariances` - the Riccati recursion of the Kalman filter (§V-A reference).
* :func:`pcrb_mc_numpy` - Monte Carlo PCRB: simulate trajectories, average eqs 5-8, run eq 4.
* :func:`pcrb_gmm_1d_numpy` - Algorithm 2 for a scalar model with Gauss-Hermite libraries, the
  linear propagator (eqs 63-64) and the k-means of Algorithm 3 (eqs 69-72), looping over time and
  k-means iterations the way the paper's pseudocode does (vectorised over components only).
"""

from __future__ import annotations

import math

import numpy as np


def kalman_covariances(F, H, Q, R, P0, n_steps):
    """Posterior covariances ``P_0..P_T`` of the Kalman filter (time-invariant system)."""
    P = np.array(P0, float)
    out = [P.copy()]
    for _ in range(n_steps):
        Pp = F @ P @ F.T + Q
        S = H @ Pp @ H.T + R
        K = Pp @ H.T @ np.linalg.inv(S)
        P = (np.eye(len(P)) - K @ H) @ Pp
        P = 0.5 * (P + P.T)
        out.append(P.copy())
    return np.stack(out)


def pcrb_step_numpy(J, D11, D12, D22):
    """Eq 4."""
    return D22 - D12.T @ np.linalg.inv(J + D11) @ D12


def pcrb_mc_numpy(f, jac_f, jac_h, Q, R, m0, P0, n_steps, n_samples, rng):
    """Monte Carlo PCRB for ``x_{n+1} = f(x_n, n) + w_n``, ``z_n = h(x_n) + v_n`` (vectorised f).

    ``f(X (N, d), n) -> (N, d)``, ``jac_f(X, n) -> (N, d, d)``, ``jac_h(X, n) -> (N, m, d)``.
    Returns the bounds ``J_n^{-1}``, ``n = 0..T``.
    """
    d = len(m0)
    Qi = np.linalg.inv(Q)
    Ri = np.linalg.inv(R)
    LQ = np.linalg.cholesky(Q)
    X = rng.multivariate_normal(m0, P0, size=n_samples)
    J = np.linalg.inv(P0)
    bounds = [np.linalg.inv(J)]
    for n in range(n_steps):
        F = jac_f(X, n)
        D11 = np.einsum("sji,jk,skl->il", F, Qi, F) / n_samples
        D12 = -F.mean(axis=0).T @ Qi
        X = f(X, n) + rng.standard_normal((n_samples, d)) @ LQ.T
        Hm = jac_h(X, n + 1)
        D22 = Qi + np.einsum("sji,jk,skl->il", Hm, Ri, Hm) / n_samples
        J = pcrb_step_numpy(J, D11, D12, D22)
        bounds.append(np.linalg.inv(J))
    return np.stack(bounds)


def gh_library(num, sigma):
    """Gauss-Hermite splitting library: normalised weights, means ``k z_i``, ``sigma``."""
    z, w = np.polynomial.hermite_e.hermegauss(num)
    return w / w.sum(), math.sqrt(1.0 - sigma**2) * z, sigma


def split_1d(w, m, v, lib):
    """Split every 1-D component ``(w, m, v)`` with a library (eq 20 in 1-D)."""
    lw, lm, ls = lib
    s = np.sqrt(v)
    W = (w[:, None] * lw[None]).ravel()
    M = (m[:, None] + s[:, None] * lm[None]).ravel()
    V = np.repeat(v * ls**2, len(lw))
    return W, M, V


def _dist(w, m, v, cw, cm, cv):
    s = w[:, None] + cw[None]
    coef = np.where(s > 0, w[:, None] * cw[None] / np.where(s > 0, s, 1.0), 0.0)
    return coef * (m[:, None] - cm[None]) ** 2 / (v[:, None] + cv[None])


def _merge(w, m, v, labels, K):
    W = np.bincount(labels, weights=w, minlength=K)
    ok = W > 0
    Wd = np.where(ok, W, 1.0)
    M = np.bincount(labels, weights=w * m, minlength=K) / Wd
    S = np.bincount(labels, weights=w * (v + m * m), minlength=K) / Wd - M * M
    return W, M, S, ok


def kmeans_1d(w, m, v, K, max_iter=100):
    """Algorithm 3 in 1-D: heaviest + farthest-point init, Lloyd iterations with eq 69."""
    idx = [int(np.argmax(w))]
    mind = _dist(w, m, v, w[idx], m[idx], v[idx])[:, 0]
    for _ in range(1, K):
        k = int(np.argmax(mind))
        idx.append(k)
        mind = np.minimum(mind, _dist(w, m, v, w[[k]], m[[k]], v[[k]])[:, 0])
    cw, cm, cv = w[idx].copy(), m[idx].copy(), v[idx].copy()
    labels = None
    for _ in range(max_iter):
        labels = np.argmin(_dist(w, m, v, cw, cm, cv), axis=1)
        W, M, S, ok = _merge(w, m, v, labels, K)
        nw, nm, nv = np.where(ok, W, cw), np.where(ok, M, cm), np.where(ok, S, cv)
        done = np.array_equal(nw, cw) and np.array_equal(nm, cm) and np.array_equal(nv, cv)
        cw, cm, cv = nw, nm, nv
        if done:
            break
    W, M, S, ok = _merge(w, m, v, labels, K)
    return W[ok], M[ok], S[ok]


def pcrb_gmm_1d_numpy(
    f,
    fprime,
    hprime,
    q,
    r,
    prior_w,
    prior_m,
    prior_v,
    J0,
    n_steps,
    K,
    state_lib,
    noise_lib,
    quad_order=40,
    max_iter=100,
):
    """Algorithm 2 (every step) for a scalar model; returns the bounds ``1/J_n``, ``n = 0..T``.

    ``f(x, n)``, ``fprime(x, n)``, ``hprime(x, n)`` act elementwise on arrays.
    """
    z, wq = np.polynomial.hermite_e.hermegauss(quad_order)
    wq = wq / wq.sum()
    w, m, v = prior_w, prior_m, prior_v
    if len(w) > K:
        w, m, v = kmeans_1d(w, m, v, K, max_iter)
    nw, nm, nv = noise_lib_split(q, noise_lib)
    J = J0
    bounds = [1.0 / J]
    for n in range(n_steps):
        X = m[:, None] + np.sqrt(v)[:, None] * z[None]
        Fx = fprime(X, n)
        D11 = np.sum(w[:, None] * wq[None] * Fx * Fx) / q
        D12 = -np.sum(w[:, None] * wq[None] * Fx) / q
        rw, rm, rv = split_1d(w, m, v, state_lib)
        fm = f(rm, n)
        Fm = fprime(rm, n)
        pw = (rw[:, None] * nw[None]).ravel()
        pm = (fm[:, None] + nm[None]).ravel()
        pv = ((Fm * Fm * rv)[:, None] + nv[None]).ravel()
        w, m, v = kmeans_1d(pw, pm, pv, K, max_iter)
        w = w / w.sum()
        X = m[:, None] + np.sqrt(v)[:, None] * z[None]
        Hx = hprime(X, n + 1)
        D22 = 1.0 / q + np.sum(w[:, None] * wq[None] * Hx * Hx) / r
        J = D22 - D12 * D12 / (J + D11)
        bounds.append(1.0 / J)
    return np.asarray(bounds)


def noise_lib_split(q, lib):
    """Split ``N(0, q)`` with a library."""
    return split_1d(np.ones(1), np.zeros(1), np.full(1, q), lib)


def pcrb_gmm_1d_small_numpy(f, fprime, hprime, q, r, w, m, v, J0, n_steps, quad_order=40):
    """Algorithm 1 (linear propagator, eqs 51-52) for a scalar model; bounds ``1/J_n``."""
    z, wq = np.polynomial.hermite_e.hermegauss(quad_order)
    wq = wq / wq.sum()
    w = w / w.sum()
    J = J0
    bounds = [1.0 / J]
    for n in range(n_steps):
        X = m[:, None] + np.sqrt(v)[:, None] * z[None]
        Fx = fprime(X, n)
        D11 = np.sum(w[:, None] * wq[None] * Fx * Fx) / q
        D12 = -np.sum(w[:, None] * wq[None] * Fx) / q
        Fm = fprime(m, n)
        m, v = f(m, n), Fm * Fm * v + q
        X = m[:, None] + np.sqrt(v)[:, None] * z[None]
        Hx = hprime(X, n + 1)
        D22 = 1.0 / q + np.sum(w[:, None] * wq[None] * Hx * Hx) / r
        J = D22 - D12 * D12 / (J + D11)
        bounds.append(1.0 / J)
    return np.asarray(bounds)
