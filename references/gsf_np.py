"""Plain NumPy Gaussian sum filter with EKF components, one run at a time (seed 000 eqs 4–18).

The per-run loop a user would otherwise write; used as the independent reference of
``gmjax.filters.gsf`` and as the NumPy baseline of ``benchmarks/bench_montecarlo.py``.
Mixtures are plain ``(weights (n,), means (n, d), covs (n, d, d))`` tuples without padding.
"""

from __future__ import annotations

import itertools
from typing import Callable

import numpy as np

Mixture = tuple[np.ndarray, np.ndarray, np.ndarray]


def _gauss_logpdf(x, m, S):
    diff = x - m
    L = np.linalg.cholesky(S)
    r = np.linalg.solve(L, diff)
    return -0.5 * r @ r - np.log(np.diag(L)).sum() - 0.5 * len(x) * np.log(2 * np.pi)


def _num_jacobian(fn, x, t, eps=1e-7):
    x = np.asarray(x, float)
    y0 = np.asarray(fn(x, t), float)
    J = np.zeros((y0.size, x.size))
    for k in range(x.size):
        dx = np.zeros_like(x)
        dx[k] = eps * max(1.0, abs(x[k]))
        J[:, k] = (np.asarray(fn(x + dx, t)) - np.asarray(fn(x - dx, t))) / (2 * dx[k])
    return J


def gsf_step(
    post: Mixture,
    z: np.ndarray,
    t: int,
    f: Callable,
    h: Callable,
    f_jac: Callable,
    h_jac: Callable,
    q: Mixture,
    r: Mixture,
) -> tuple[Mixture, float]:
    """One predict + update of the EKF-based GSF; returns the updated mixture and ``log p(z)``."""
    w, m, P = post
    qw, qm, qP = q
    rw, rm, rP = r
    pw, pm, pP = [], [], []
    for i in range(len(w)):  # eqs 4-8
        F = f_jac(m[i], t)
        fm = f(m[i], t)
        for l in range(len(qw)):
            pw.append(w[i] * qw[l])
            pm.append(fm + qm[l])
            pP.append(F @ P[i] @ F.T + qP[l])
    if np.any(np.isnan(z)):
        pw = np.array(pw)
        return (pw / pw.sum(), np.array(pm), np.array(pP)), 0.0
    uw, um, uP = [], [], []
    for i in range(len(pw)):  # eqs 9-16
        H = h_jac(pm[i], t)
        hm = h(pm[i], t)
        for j in range(len(rw)):
            zhat = hm + rm[j]
            S = H @ pP[i] @ H.T + rP[j]
            K = pP[i] @ H.T @ np.linalg.inv(S)
            uw.append(np.log(pw[i] * rw[j]) + _gauss_logpdf(z, zhat, S))
            um.append(pm[i] + K @ (z - zhat))
            Pn = pP[i] - K @ H @ pP[i]
            uP.append(0.5 * (Pn + Pn.T))
    uw = np.array(uw)
    top = uw.max()
    log_norm = top + np.log(np.exp(uw - top).sum())
    return (np.exp(uw - log_norm), np.array(um), np.array(uP)), float(log_norm)


def moments(mix: Mixture) -> tuple[np.ndarray, np.ndarray]:
    """Eqs 17–18."""
    w, m, P = mix
    w = w / w.sum()
    mu = w @ m
    dev = m - mu
    return mu, np.einsum("k,kij->ij", w, P) + np.einsum("k,ki,kj->ij", w, dev, dev)


def keep_heaviest(mix: Mixture, n: int) -> Mixture:
    """Number-limited pruning (NL-GMR): the ``n`` heaviest, renormalised."""
    w, m, P = mix
    idx = np.argsort(-w, kind="stable")[:n]
    return w[idx] / w[idx].sum(), m[idx], P[idx]


def run_gsf(
    prior: Mixture,
    zs: np.ndarray,
    f: Callable,
    h: Callable,
    q: Mixture,
    r: Mixture,
    *,
    reducer: Callable[[Mixture], Mixture] | None = None,
    f_jac: Callable | None = None,
    h_jac: Callable | None = None,
) -> tuple[np.ndarray, np.ndarray, list[Mixture]]:
    """Filter ``zs (T, m)`` with ``t = 1..T``; returns estimates ``(T, d)``, covariances and posteriors."""
    f_jac = f_jac or (lambda x, t: _num_jacobian(f, x, t))
    h_jac = h_jac or (lambda x, t: _num_jacobian(h, x, t))
    post = prior
    ests, covs, posts = [], [], []
    for k, z in enumerate(zs):
        full, _ = gsf_step(post, z, k + 1, f, h, f_jac, h_jac, q, r)
        mu, C = moments(full)
        ests.append(mu)
        covs.append(C)
        post = full if reducer is None else reducer(full)
        posts.append(post)
    return np.array(ests), np.array(covs), posts


def enumerate_linear_posterior(
    prior: Mixture, zs: np.ndarray, F: np.ndarray, H: np.ndarray, q: Mixture, r: Mixture
) -> Mixture:
    """Exact posterior of a linear model with GM noises by enumerating every noise history.

    Each history ``(i_0, l_1, j_1, ..., l_T, j_T)`` is one Kalman filter run; its weight is the
    product of the prior/noise weights and the measurement likelihoods. Independent of the
    step-wise GSF recursion (it never forms intermediate mixtures).
    """
    pw, pm, pP = prior
    qw, qm, qP = q
    rw, rm, rP = r
    T = len(zs)
    logw, means, covs = [], [], []
    choices = [range(len(pw))] + [range(len(qw)), range(len(rw))] * T
    for hist in itertools.product(*choices):
        i0, rest = hist[0], hist[1:]
        m, P = pm[i0].copy(), pP[i0].copy()
        lw = np.log(pw[i0])
        for k in range(T):
            l, j = rest[2 * k], rest[2 * k + 1]
            m = F @ m + qm[l]
            P = F @ P @ F.T + qP[l]
            zhat = H @ m + rm[j]
            S = H @ P @ H.T + rP[j]
            K = P @ H.T @ np.linalg.inv(S)
            lw += np.log(qw[l] * rw[j]) + _gauss_logpdf(zs[k], zhat, S)
            m = m + K @ (zs[k] - zhat)
            P = P - K @ H @ P
        logw.append(lw)
        means.append(m)
        covs.append(0.5 * (P + P.T))
    logw = np.array(logw)
    w = np.exp(logw - logw.max())
    return w / w.sum(), np.array(means), np.array(covs)
