"""Plain NumPy AGSSCKF (seed 001, Table 1), one run at a time, written from the paper.

The independent reference of :mod:`gmjax.filters.agsf` and the NumPy baseline of
``benchmarks/bench_seed001.py``. It follows Table 1 step by step with Python loops over the
components and the same readings as gmjax (documented in ``gmjax/filters/agsf.py``): splitting
while ``N < N_max`` with eq 31's levels limited so that ``N <= min(N_max, capacity)``, the eq 34–35
weights, the global estimate of eqs 36–38, pruning and the three merge rules of Step 6 with the
history of the previous step, and the eq 40–41 prediction. The sub-filters are cubature Kalman
filters in covariance form, algebraically identical to the square-root form of eqs 8–22.

Slots are kept in a fixed-capacity list so the order of components (which decides ties in the
greedy merge) is the one gmjax uses: predicted slot ``j = l N + j'`` (eq 41), split children in
the split slot and then the free slots in increasing order, merges into the lower slot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np


@dataclass
class Config:
    n_max: int = 15
    capacity: int | None = None
    max_level: int = 3
    psi_th: float = 0.02
    r: float = 1.5
    l: float = 0.5  # noqa: E741
    w: float = 0.5
    prune_threshold: float = 1e-4
    low_weight: float = 0.01
    merge_threshold: float = 0.1
    merge_don: float = 0.004


@dataclass
class Slots:
    """Fixed-capacity component list: ``live[i]`` says whether slot ``i`` holds a component."""

    w: np.ndarray
    m: np.ndarray
    P: np.ndarray
    live: np.ndarray
    parent: np.ndarray = field(default=None)


def cubature_points(m: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``X_i = m + S xi_i``, ``xi = sqrt(d) [I, -I]`` (eq 26); rows are points."""
    d = m.shape[0]
    S = np.linalg.cholesky(P)
    cols = math.sqrt(d) * S.T
    return np.concatenate([m + cols, m - cols])


def don(h: Callable, m: np.ndarray, P: np.ndarray, t) -> float:
    """Eqs 26–29."""
    d = m.shape[0]
    X = cubature_points(m, P)
    Z = np.array([np.atleast_1d(h(x, t)) for x in X])
    h0 = np.atleast_1d(h(m, t))
    psi = [0.5 * np.sum((Z[i] + Z[i + d] - 2 * h0) ** 2) for i in range(d)]
    return float(np.mean(psi))


def ckf_predict(f, m, P, t, qm, qP):
    """Eqs 8–12 (covariance form)."""
    X = cubature_points(m, P)
    Y = np.array([np.atleast_1d(f(x, t)) for x in X])
    m0 = Y.mean(0)
    dY = Y - m0
    return m0 + qm, dY.T @ dY / len(X) + qP


def ckf_update(h, m, P, z, t, rm, rP):
    """Eqs 13–22 (covariance form); returns ``(m+, P+, log N(z; z_hat, S))``."""
    X = cubature_points(m, P)
    Z = np.array([np.atleast_1d(h(x, t)) for x in X])
    z0 = Z.mean(0)
    dZ = Z - z0
    n = len(X)
    S = dZ.T @ dZ / n + rP
    Pxz = (X - m).T @ dZ / n
    K = Pxz @ np.linalg.inv(S)
    y = z - z0 - rm
    L = np.linalg.cholesky(S)
    r = np.linalg.solve(L, y)
    ll = -0.5 * r @ r - np.log(np.diag(L)).sum() - 0.5 * len(y) * np.log(2 * np.pi)
    return m + K @ y, P - K @ S @ K.T, float(ll)


def principal_axis(P):
    lam, V = np.linalg.eigh(0.5 * (P + P.T))
    e = V[:, -1]
    i = int(np.argmax(np.abs(e)))
    if e[i] < 0:
        e = -e
    return max(lam[-1], 0.0), e


def split_levels(w, m, P, n_levels, l, omega):  # noqa: E741
    """Eq 32 repeated ``n_levels`` times; children in tree order (``2c``: +, ``2c+1``: -)."""
    kids = [(w, m, P)]
    for _ in range(n_levels):
        new = []
        for wc, mc, Pc in kids:
            lam, e = principal_axis(Pc)
            a = math.sqrt(lam) * e
            Pn = Pc - l * l * np.outer(a, a)
            Pn = 0.5 * (Pn + Pn.T)
            new.append((omega * wc, mc + l * a, Pn))
            new.append(((1 - omega) * wc, mc - l * a, Pn.copy()))
        kids = new
    return kids


def merge(w1, m1, P1, w2, m2, P2):
    """Eq 39 (normalised so it preserves the pair's mean and covariance)."""
    W = w1 + w2
    l1, l2 = (w1 / W, w2 / W) if W > 0 else (0.5, 0.5)
    mm = l1 * m1 + l2 * m2
    dd = m1 - m2
    PP = l1 * P1 + l2 * P2 + l1 * l2 * np.outer(dd, dd)
    return W, mm, 0.5 * (PP + PP.T)


def pair_cost(w1, m1, P1, w2, m2, P2) -> float:
    """Weight-normalised Runnalls bound of merging a pair."""
    W, _, Pm = merge(w1, m1, P1, w2, m2, P2)
    l1, l2 = (w1 / W, w2 / W) if W > 0 else (0.5, 0.5)
    ld = lambda A: np.linalg.slogdet(A)[1]  # noqa: E731
    return max(0.5 * (ld(Pm) - l1 * ld(P1) - l2 * ld(P2)), 0.0)


class AGSSCKF:
    """The filter: ``init(prior)``, then ``step(z, t) -> (mean, cov, info)`` per time step."""

    def __init__(self, f, h, q, r, cfg: Config = Config()):  # noqa: B008 (never mutated)
        self.f, self.h, self.cfg = f, h, cfg
        self.qw, self.qm, self.qP = [np.asarray(a, float) for a in q]
        self.qw = self.qw / self.qw.sum()
        rw, rm, rP = [np.asarray(a, float) for a in r]
        assert len(rw) == 1
        self.rm, self.rP = rm[0], rP[0]
        self.Q = len(self.qw)
        self.C = cfg.n_max if cfg.capacity is None else cfg.capacity
        self.K = self.C // self.Q
        self.N_lim = min(cfg.n_max, self.C)

    def init(self, prior):
        w, m, P = [np.asarray(a, float) for a in prior]
        n = len(w)
        assert n <= self.K
        d = m.shape[1]
        self.post_w = np.zeros(self.K)
        self.post_w[:n] = w / w.sum()
        self.post_m = np.zeros((self.K, d))
        self.post_m[:n] = m
        self.post_P = np.tile(np.eye(d), (self.K, 1, 1))
        self.post_P[:n] = P
        self.post_live = np.zeros(self.K, bool)
        self.post_live[:n] = True
        self.post_don = np.full(self.K, np.inf)

    # Step 7 (eqs 40-41)
    def predict(self, t) -> Slots:
        C, K, Q = self.C, self.K, self.Q
        d = self.post_m.shape[1]
        s = Slots(
            np.zeros(C), np.zeros((C, d)), np.tile(np.eye(d), (C, 1, 1)), np.zeros(C, bool), np.zeros(C, int)
        )
        for l in range(Q):  # noqa: E741
            for jp in range(K):
                j = l * K + jp
                s.parent[j] = jp
                if not self.post_live[jp]:
                    continue
                s.m[j], s.P[j] = ckf_predict(
                    self.f, self.post_m[jp], self.post_P[jp], t, self.qm[l], self.qP[l]
                )
                s.w[j] = self.post_w[jp] * self.qw[l]
                s.live[j] = True
        return s

    def _level(self, psi, N) -> int:
        cfg = self.cfg
        n = 0
        for k in range(1, cfg.max_level + 1):
            if psi >= cfg.psi_th * cfg.r ** (k - 1) and N - 1 + 2**k <= self.N_lim:
                n = k
            else:
                break
        return n

    def step(self, z, t):
        cfg = self.cfg
        s = self.predict(t)
        C = self.C
        missing = bool(np.any(np.isnan(z)))
        # Steps 2-3
        n_split = 0
        if cfg.max_level > 0:
            for _ in range(self.N_lim):
                psis = [don(self.h, s.m[i], s.P[i], t) if s.live[i] else -np.inf for i in range(C)]
                m = int(np.argmax(psis))
                n = self._level(psis[m], int(s.live.sum()))
                if n == 0 or missing:
                    break
                kids = split_levels(s.w[m], s.m[m], s.P[m], n, cfg.l, cfg.w)
                free = [i for i in range(C) if not s.live[i]]
                for c, (wc, mc, Pc) in enumerate(kids):
                    dest = m if c == 0 else free[c - 1]
                    s.w[dest], s.m[dest], s.P[dest], s.live[dest] = wc, mc, Pc, True
                    s.parent[dest] = s.parent[m]
                n_split += 1
        don_now = np.array([don(self.h, s.m[i], s.P[i], t) if s.live[i] else 0.0 for i in range(C)])
        n_updated = int(s.live.sum())
        # Step 4 (eqs 33-35)
        logw = np.full(C, -np.inf)
        for i in range(C):
            if not s.live[i]:
                continue
            if missing:
                logw[i] = np.log(s.w[i])
                continue
            s.m[i], s.P[i], ll = ckf_update(self.h, s.m[i], s.P[i], z, t, self.rm, self.rP)
            logw[i] = np.log(s.w[i]) + ll
        mx = logw[s.live].max()
        s.w = np.where(s.live, np.exp(logw - mx), 0.0)
        s.w /= s.w.sum()
        # Step 5 (eqs 36-38)
        W = s.w[s.live]
        mean = W @ s.m[s.live]
        dm = s.m[s.live] - mean
        cov = np.einsum("k,kij->ij", W, s.P[s.live]) + np.einsum("k,ki,kj->ij", W, dm, dm)
        # Step 6: pruning
        heaviest = int(np.argmax(np.where(s.live, s.w, -np.inf)))
        keep = s.live & ((s.w >= cfg.prune_threshold) | (np.arange(C) == heaviest))
        s.live = keep
        s.w = np.where(keep, s.w, 0.0)
        s.w /= s.w.sum()
        # Step 6: merge rules 1-3 with the previous step's history
        par = s.parent
        low_before = np.array([self.post_w[par[i]] < cfg.low_weight for i in range(C)])
        low_don = np.array(
            [don_now[i] < cfg.merge_don and self.post_don[par[i]] < cfg.merge_don for i in range(C)]
        )
        dons = don_now.copy()

        def before_cost(a, b):
            if a == b:
                return 0.0
            return pair_cost(
                self.post_w[a], self.post_m[a], self.post_P[a], self.post_w[b], self.post_m[b], self.post_P[b]
            )

        for _ in range(C - 1):
            best, bi, bj = np.inf, -1, -1
            for i in range(C):
                for j in range(i + 1, C):
                    if not (s.live[i] and s.live[j]):
                        continue
                    c = pair_cost(s.w[i], s.m[i], s.P[i], s.w[j], s.m[j], s.P[j])
                    r1 = (
                        s.w[i] < cfg.low_weight
                        and low_before[i]
                        and s.w[j] < cfg.low_weight
                        and low_before[j]
                    )
                    r2 = c < cfg.merge_threshold and before_cost(par[i], par[j]) < cfg.merge_threshold
                    r3 = low_don[i] and low_don[j]
                    if (r1 or r2 or r3) and c < best:
                        best, bi, bj = c, i, j
            if bi < 0:
                break
            heavier = par[bj] if s.w[bj] > s.w[bi] else par[bi]
            s.w[bi], s.m[bi], s.P[bi] = merge(s.w[bi], s.m[bi], s.P[bi], s.w[bj], s.m[bj], s.P[bj])
            s.live[bj] = False
            s.w[bj] = 0.0
            par[bi] = heavier
            low_before[bi] = low_before[bi] and low_before[bj]
            low_don[bi] = low_don[bi] and low_don[bj]
            dons[bi] = max(dons[bi], dons[bj])
        # fit to the posterior slots (heaviest if too many), renormalise
        idx = [i for i in range(C) if s.live[i]]
        truncated = len(idx) > self.K
        if truncated:
            idx = sorted(idx, key=lambda i: (-s.w[i], i))[: self.K]
        d = s.m.shape[1]
        self.post_w = np.zeros(self.K)
        self.post_m = np.zeros((self.K, d))
        self.post_P = np.tile(np.eye(d), (self.K, 1, 1))
        self.post_live = np.zeros(self.K, bool)
        self.post_don = np.full(self.K, np.inf)
        for k, i in enumerate(idx):
            self.post_w[k], self.post_m[k], self.post_P[k] = s.w[i], s.m[i], s.P[i]
            self.post_live[k] = True
            self.post_don[k] = dons[i]
        self.post_w /= self.post_w.sum()
        info = dict(n_split=n_split, n_updated=n_updated, n_components=len(idx), truncated=truncated)
        return mean, cov, info


def run(filt: AGSSCKF, prior, zs, ts):
    """Filter a whole sequence; returns ``(means (T, d), covs (T, d, d), infos)``."""
    filt.init(prior)
    means, covs, infos = [], [], []
    for z, t in zip(zs, ts):
        mu, P, info = filt.step(np.asarray(z, float), t)
        means.append(mu)
        covs.append(P)
        infos.append(info)
    return np.array(means), np.array(covs), infos
