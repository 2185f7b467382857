"""Minimal hand-written JAX Gaussian sum filters: the practical speed limit for gmjax's GSF step.

Plain ``jax.numpy`` with no generic machinery: no mixture type, no masks (a dead slot is a log weight of
``-inf``), no flags, no validation, no reducer protocol. They do the same arithmetic as
``gmjax.filters.gsf.build_gsf`` with EKF components (seed 000 eqs 4–18: predict every component ×
every process-noise component, update every predicted component × every measurement-noise component,
Joseph-form covariance, estimate = moments of the updated mixture) followed by

* NL-GSF: keep the ``K`` heaviest (``lax.top_k``) and renormalise;
* R-GSF: Runnalls' greedy pairwise merging down to ``K`` (the KL upper-bound cost of seed 003 eq 11),
  with the cost matrix computed once and one row/column refreshed per merge.

``benchmarks/bench_gsf_kernel.py`` times them beside gmjax in one process and checks that the
estimates agree to 1e-9. Only the robustness work a minimal kernel would skip is missing here
(covariance repair, flags, non-finite measurement handling).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve, solve_triangular
from jax.scipy.special import logsumexp

Mix = tuple[jax.Array, jax.Array, jax.Array]  # (log_w (n,), means (n, d), covs (n, n, d))
_LOG_2PI = 1.8378770664093453


def _chol(S):
    """Lower Cholesky factor of ``S (..., d, d)``: unrolled for ``d <= 4`` (XLA's CPU LAPACK call per tiny
    matrix costs more than the arithmetic), ``jnp.linalg.cholesky`` above."""
    d = S.shape[-1]
    if d > 4:
        return jnp.linalg.cholesky(S)
    L = [[jnp.zeros_like(S[..., 0, 0]) for _ in range(d)] for _ in range(d)]
    for i in range(d):
        for j in range(i + 1):
            acc = S[..., i, j] - sum((L[i][k] * L[j][k] for k in range(j)), jnp.zeros_like(S[..., 0, 0]))
            L[i][j] = jnp.sqrt(acc) if i == j else acc / L[j][j]
    return jnp.stack([jnp.stack(row, -1) for row in L], -2)


def _solve_lower(L, b):
    """``L^{-1} b`` for ``b (d,)`` or ``(d, n)``: forward substitution, unrolled for ``d <= 4`` (a batched
    ``solve_triangular`` calls LAPACK once per tiny matrix on CPU)."""
    d = L.shape[-1]
    if d > 4:
        return solve_triangular(L, b, lower=True)
    xs = []
    for i in range(d):
        xs.append((b[i] - sum((L[i, k] * xs[k] for k in range(i)), jnp.zeros_like(b[i]))) / L[i, i])
    return jnp.stack(xs, 0)


def _cho_solve(L, b):
    """``(L L^T)^{-1} b``: forward then back substitution, unrolled for ``d <= 4``."""
    d = L.shape[-1]
    if d > 4:
        return cho_solve((L, True), b)
    y = _solve_lower(L, b)
    xs = [None] * d
    for i in reversed(range(d)):
        xs[i] = (y[i] - sum((L[k, i] * xs[k] for k in range(i + 1, d)), jnp.zeros_like(y[i]))) / L[i, i]
    return jnp.stack(xs, 0)


def _logdet(P):
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(_chol(P), axis1=-2, axis2=-1)), -1)


def _predict(f, F, log_w, m, P, t, q: Mix):
    """Every component × every noise component: ``(K·L)`` children, child ``i*L + l``."""
    q_logw, q_m, q_P = q
    fm = jax.vmap(f, (0, None))(m, t)
    Fm = jax.vmap(F, (0, None))(m, t)
    FPF = Fm @ P @ jnp.swapaxes(Fm, -1, -2)
    d = m.shape[-1]
    means = (fm[:, None, :] + q_m[None]).reshape(-1, d)
    covs = (FPF[:, None] + q_P[None]).reshape(-1, d, d)
    return (log_w[:, None] + q_logw[None]).reshape(-1), means, covs


def _update(h, H, log_w, m, P, z, t, r: Mix):
    """Every component × every measurement-noise component, Joseph form; weights normalised."""
    r_logw, r_m, r_P = r
    hm = jax.vmap(h, (0, None))(m, t)  # (n, mz)
    Hm = jax.vmap(H, (0, None))(m, t)  # (n, mz, d)

    def one(m_i, P_i, hm_i, H_i, rm_j, rP_j):
        S = H_i @ P_i @ H_i.T + rP_j
        L = _chol(S)
        y = z - hm_i - rm_j
        gain = _cho_solve(L, H_i @ P_i).T
        A = jnp.eye(m_i.shape[0], dtype=P_i.dtype) - gain @ H_i
        cov = A @ P_i @ A.T + gain @ rP_j @ gain.T
        r_ = _solve_lower(L, y)
        ll = -0.5 * (y.shape[0] * _LOG_2PI + r_ @ r_) - jnp.sum(jnp.log(jnp.diagonal(L)))
        return m_i + gain @ y, 0.5 * (cov + cov.T), ll

    inner = jax.vmap(one, (None, None, None, None, 0, 0))
    means, covs, ll = jax.vmap(inner, (0, 0, 0, 0, None, None))(m, P, hm, Hm, r_m, r_P)
    d = m.shape[-1]
    log_w = (log_w[:, None] + r_logw[None] + ll).reshape(-1)
    log_w = log_w - logsumexp(log_w)
    return log_w, means.reshape(-1, d), covs.reshape(-1, d, d)


def _moments(log_w, m, P):
    w = jnp.exp(log_w)
    mu = w @ m
    dev = m - mu
    return mu, jnp.einsum("k,kij->ij", w, P) + jnp.einsum("k,ki,kj->ij", w, dev, dev)


def _keep_top(log_w, m, P, k: int):
    top, idx = jax.lax.top_k(log_w, k)
    return top - logsumexp(top), m[idx], P[idx]


def _runnalls_cost(w, m, P, logdet):
    """``B(i, j)`` (seed 003 eq 11) for all pairs ``(n, n)``; ``+inf`` on the diagonal and dead slots."""
    wi, wj = w[:, None], w[None, :]
    s = wi + wj
    a, b = wi / s, wj / s
    dm = m[:, None, :] - m[None, :, :]
    Pm = (
        a[..., None, None] * P[:, None]
        + b[..., None, None] * P[None, :]
        + (a * b)[..., None, None] * (dm[..., :, None] * dm[..., None, :])
    )
    ld = _logdet(Pm)
    cost = 0.5 * (s * ld - wi * logdet[:, None] - wj * logdet[None, :])
    dead = (w[:, None] <= 0) | (w[None, :] <= 0) | jnp.eye(w.shape[0], dtype=bool)
    return jnp.where(dead, jnp.inf, cost)


def _runnalls(log_w, m, P, k: int):
    """Greedy Runnalls to ``k`` components: ``n - k`` merge steps (a static trip count; a step with at
    most ``k`` live components left changes nothing), each merging the first
    minimiser of the full cost matrix in row-major order (as gmjax); then the live slots compacted,
    heaviest first. Only row and column ``i`` of the cost matrix are recomputed per merge.
    """
    n = log_w.shape[0]
    ar = jnp.arange(n)
    w = jnp.exp(log_w)
    logdet = _logdet(P)
    upper = ar[:, None] < ar[None, :]
    cost = jnp.where(upper, _runnalls_cost(w, m, P, logdet), jnp.inf)

    def merge(_, carry):
        w, m, P, logdet, cost = carry
        flat = jnp.argmin(cost)
        i, j = flat // n, flat % n
        do = jnp.isfinite(cost.reshape(-1)[flat]) & (jnp.sum(w > 0) > k)
        s = w[i] + w[j]
        a, b = w[i] / s, w[j] / s
        dm = m[i] - m[j]
        Pn = a * P[i] + b * P[j] + a * b * jnp.outer(dm, dm)
        at_i, at_j = (ar == i) & do, (ar == j) & do
        w = jnp.where(at_i, s, jnp.where(at_j, 0.0, w))
        m = jnp.where(at_i[:, None], a * m[i] + b * m[j], m)
        P = jnp.where(at_i[:, None, None], Pn, P)
        logdet = jnp.where(at_i, _logdet(Pn), logdet)
        row = _runnalls_row(i, w, m, P, logdet)
        ii, jj = jnp.where(do, i, n), jnp.where(do, j, n)  # out of range: no write
        inf = jnp.full((n,), jnp.inf, cost.dtype)
        cost = cost.at[ii, :].set(jnp.where(ar > i, row, jnp.inf), mode="drop")
        cost = cost.at[:, ii].set(jnp.where(ar < i, row, jnp.inf), mode="drop")
        cost = cost.at[jj, :].set(inf, mode="drop").at[:, jj].set(inf, mode="drop")
        return w, m, P, logdet, cost

    w, m, P, _, _ = jax.lax.fori_loop(0, n - k, merge, (w, m, P, logdet, cost))
    top, idx = jax.lax.top_k(jnp.where(w > 0, w, -1.0), k)  # live slots, heaviest first
    log_w = jnp.where(top > 0, jnp.log(jnp.maximum(top, 1e-300)), -jnp.inf)
    return log_w - logsumexp(log_w), m[idx], P[idx]


def _runnalls_row(i, w, m, P, logdet):
    wi, s = w[i], w[i] + w
    a, b = wi / s, w / s
    dm = m[i][None, :] - m
    Pm = (
        a[:, None, None] * P[i][None]
        + b[:, None, None] * P
        + (a * b)[:, None, None] * (dm[:, :, None] * dm[:, None, :])
    )
    ld = _logdet(Pm)
    cost = 0.5 * (s * ld - wi * logdet[i] - w * logdet)
    dead = (w <= 0) | (jnp.arange(w.shape[0]) == i)
    return jnp.where(dead, jnp.inf, cost)


def minimal_gsf(
    f: Callable,
    h: Callable,
    prior: Mix,
    q: Mix,
    r: Mix,
    capacity: int,
    reducer: str = "prune",
) -> Callable[[jax.Array, jax.Array], tuple[jax.Array, jax.Array]]:
    """``run(zs (T, mz), ts (T,)) -> (means (T, d), covs (T, d, d))`` of an EKF-based GSF.

    Args:
        f, h: ``f(x (d,), t)``, ``h(x (d,), t)``.
        prior, q, r: ``(log_w, means, covs)`` of the prior (padded to ``capacity`` with ``-inf`` log
            weights), the process noise and the measurement noise (normalised log weights).
        capacity: ``K``, the posterior's slots.
        reducer: ``"prune"`` (keep the ``K`` heaviest) or ``"runnalls"``.
    """
    F, H = jax.jacfwd(f), jax.jacfwd(h)
    reduce = {"prune": _keep_top, "runnalls": _runnalls}[reducer]

    def step(carry, zt):
        z, t = zt
        log_w, m, P = _predict(f, F, *carry, t, q)
        log_w, m, P = _update(h, H, log_w, m, P, z, t, r)
        est = _moments(log_w, m, P)
        return reduce(log_w, m, P, capacity), est

    def run(zs, ts):
        _, (means, covs) = jax.lax.scan(step, prior, (zs, ts))
        return means, covs

    return run
