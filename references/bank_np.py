"""Plain NumPy linear GSF bank with the reductions of seed 004, one run at a time.

Written straight from Pishdad & Labeau's equations with Python loops over the models ``(i, j)`` and
over time: the bank of Kalman filters (eqs 5–9), GSF-merge (eqs 10–11), GSF-remove (eqs 12–14),
the Matched filter, the Kalman filter on moment-matched noises, and the active-cluster reduction
(eqs 15–17) with the initial estimates GSF-merge, GSF-remove, preloaded gains, steady-state gains
(``scipy.linalg.solve_discrete_are``) and one moment-matched Kalman step. The reference of
``gmjax.filters.bank`` and the NumPy baseline of ``benchmarks/bench_seed004.py``.

Noise clusters are lists ``(weights (n,), means (n, k), covs (n, k, k))``. For a process noise
``v = G v_s`` (eq 20) pass ``G`` ``(d, q)``: eq 17 then scores the least-squares ``v_s`` against the
scalar clusters ``(G^+ u^i, G^+ Q^i G^{+T})``.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_discrete_are


def _logpdf(x, m, S):
    x = np.atleast_1d(x)
    diff = x - m
    L = np.linalg.cholesky(S)
    r = np.linalg.solve(L, diff)
    return -0.5 * r @ r - np.log(np.diag(L)).sum() - 0.5 * len(x) * np.log(2 * np.pi)


def _kf(m, P, z, F, H, u, Q, b, R):
    """One Kalman step for model (u, Q, b, R): predicted + posterior moments, log-likelihood."""
    mp = F @ m + u
    Pp = F @ P @ F.T + Q
    S = H @ Pp @ H.T + R
    K = Pp @ H.T @ np.linalg.inv(S)
    y = z - H @ mp - b
    A = np.eye(len(m)) - K @ H
    Pn = A @ Pp @ A.T + K @ R @ K.T
    return mp + K @ y, Pn, _logpdf(y, np.zeros_like(y), S)


def _dare(F, H, Q, R):
    """Steady-state predicted covariance: SciPy's DARE solver, or (where it reports an
    ill-conditioned pencil, e.g. the rank-one ``Q`` of eq 22) the Riccati iteration to convergence."""
    try:
        return solve_discrete_are(F.T, H.T, Q, R)
    except (ValueError, np.linalg.LinAlgError):
        P = Q.copy()
        for _ in range(1_000_000):
            S = H @ P @ H.T + R
            Pn = F @ (P - P @ H.T @ np.linalg.inv(S) @ H @ P) @ F.T + Q
            if np.max(np.abs(Pn - P)) <= 1e-14 * np.max(np.abs(Pn)):
                return Pn
            P = Pn
        raise RuntimeError("Riccati iteration did not converge") from None


def _moments(w, means, covs):
    w = np.asarray(w, float) / np.sum(w)
    mu = sum(wi * mi for wi, mi in zip(w, means))
    cov = sum(wi * (Pi + np.outer(mi - mu, mi - mu)) for wi, mi, Pi in zip(w, means, covs))
    return mu, cov


def bank_filter_np(method, zs, F, H, process, measurement, prior, *, active=None, G=None):
    """Run one bank method over ``zs`` ``(T, m)``; returns the posterior means ``(T, d)``."""
    qw, qu, qQ = (np.asarray(a, float) for a in process)
    rw, rb, rR = (np.asarray(a, float) for a in measurement)
    qw, rw = qw / qw.sum(), rw / rw.sum()
    L, J = len(qw), len(rw)
    m, P = (np.asarray(a, float) for a in prior)
    d = len(m)
    Gp = np.eye(d) if G is None else np.linalg.pinv(np.asarray(G, float))
    q_mm = _moments(qw, qu, qQ)
    r_mm = _moments(rw, rb, rR)
    if method == "kf-mm":
        qw, qu, qQ = np.ones(1), q_mm[0][None], q_mm[1][None]
        rw, rb, rR = np.ones(1), r_mm[0][None], r_mm[1][None]
        L = J = 1
    Qbar = np.einsum("k,kij->ij", qw, qQ)
    Rbar = np.einsum("k,kij->ij", rw, rR)
    Pbar = P.copy()
    ss = {}
    if method == "red-ssg":
        for i in range(L):
            for j in range(J):
                Pss = _dare(F, H, qQ[i], rR[j])
                S = H @ Pss @ H.T + rR[j]
                ss[i, j] = (Pss @ H.T @ np.linalg.inv(S), S)
    out = []
    for k, z in enumerate(np.asarray(zs, float)):
        post = {}
        for i in range(L):
            for j in range(J):
                mij, Pij, ll = _kf(m, P, z, F, H, qu[i], qQ[i], rb[j], rR[j])
                post[i, j] = (mij, Pij, np.log(qw[i]) + np.log(rw[j]) + ll)
        lw = np.array([post[i, j][2] for i in range(L) for j in range(J)])
        mu = np.exp(lw - lw.max())
        mu /= mu.sum()  # eq 9
        keys = [(i, j) for i in range(L) for j in range(J)]
        merged = sum(mu[n] * post[key][0] for n, key in enumerate(keys))  # eq 10
        best = keys[int(np.argmax(mu))]  # eq 12
        # preloaded-gain recursion (Red-PKG)
        Pbar_p = F @ Pbar @ F.T + Qbar
        Sbar = H @ Pbar_p @ H.T + Rbar
        Kbar = Pbar_p @ H.T @ np.linalg.inv(Sbar)
        Abar = np.eye(d) - Kbar @ H
        Pbar = Abar @ Pbar_p @ Abar.T + Kbar @ Rbar @ Kbar.T
        if method == "gsf-merge":
            covs = [post[key][1] for key in keys]
            m, P = _moments(mu, [post[key][0] for key in keys], covs)  # eqs 10-11
            out.append(m)
            continue
        if method in ("gsf-remove", "kf-mm"):
            sel = best
        elif method == "matched":
            sel = (int(active[k][0]), int(active[k][1]))
        else:
            if method == "red-gsfm":
                x_check = merged
            elif method == "red-gsfr":
                x_check = post[best][0]
            elif method in ("red-pkg", "red-ssg"):
                xs, lls = [], []
                for i in range(L):
                    for j in range(J):
                        Kg, S = (Kbar, Sbar) if method == "red-pkg" else ss[i, j]
                        mp = F @ m + qu[i]
                        y = z - H @ mp - rb[j]
                        xs.append(mp + Kg @ y)
                        lls.append(np.log(qw[i]) + np.log(rw[j]) + _logpdf(y, np.zeros_like(y), S))
                lls = np.array(lls)
                wts = np.exp(lls - lls.max())
                x_check = sum(wt * x for wt, x in zip(wts / wts.sum(), xs))
            elif method == "red-dkg":
                x_check = _kf(m, P, z, F, H, q_mm[0], q_mm[1], r_mm[0], r_mm[1])[0]
            else:
                raise ValueError(f"method: unknown {method!r}")
            v = Gp @ (x_check - F @ m)  # eq 15
            w = z - H @ x_check  # eq 16
            si = [np.log(qw[i]) + _logpdf(v, Gp @ qu[i], Gp @ qQ[i] @ Gp.T) for i in range(L)]
            sj = [np.log(rw[j]) + _logpdf(w, rb[j], rR[j]) for j in range(J)]
            sel = (int(np.argmax(si)), int(np.argmax(sj)))  # eq 17
        m, P = post[sel][0], post[sel][1]  # eqs 13-14
        out.append(m)
    return np.array(out)
