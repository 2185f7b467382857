"""Minimal hand-written JAX Gaussian sum filters: the practical speed limit for gmjax's GSF step.

Plain ``jax.numpy`` with no generic machinery: no mixture type, no masks (a dead slot is a log weight of
``-inf``), no flags, no validation, no reducer protocol. They do the same arithmetic as
``gmjax.filters.gsf.build_gsf`` with EKF components (seed 000 eqs 4–18: predict every component ×
every process-noise component, update every predicted component × every measurement-noise component,
Joseph-form covariance, estimate = moments of the updated mixture) followed by

* NL-GSF: keep the ``K`` heaviest (``lax.top_k``) and renormalise;
* R-GSF: Runnalls' greedy pairwise merging down to ``K`` (the KL upper-bound cost of seed 003 eq 11),
  with the cost matrix computed once and one row/column refreshed per merge.
* PCM-GSF (grid): seed 000's prune-cluster-merge with the grid confidence search and no Newton
  steps, as ``gmjax.reduction.PCM(max_components=K, capacity=K, newton_steps=0)``: clusters are
  ``uint32`` bitmasks (``K <= 32``), one ``while_loop`` visits only the overlapping cluster pairs of
  all grid points, and what does not depend on ``λ`` is computed once per step (see :func:`_pcm`).

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
    """``log det P``: for ``d <= 4`` the logs of the ``L D L^T`` pivots (no square roots: 2-3x faster
    than the logs of a Cholesky diagonal under ``vmap``, as ``gmjax.gaussian.spd_logdet``)."""
    d = P.shape[-1]
    if d > 4:
        return 2.0 * jnp.sum(jnp.log(jnp.diagonal(_chol(P), axis1=-2, axis2=-1)), -1)
    unit = [[None] * d for _ in range(d)]
    pivots = []
    for j in range(d):
        dj = P[..., j, j] - sum(
            (unit[j][k] * unit[j][k] * pivots[k] for k in range(j)), jnp.zeros_like(P[..., 0, 0])
        )
        pivots.append(dj)
        for i in range(j + 1, d):
            v = P[..., i, j] - sum(
                (unit[i][k] * unit[j][k] * pivots[k] for k in range(j)), jnp.zeros_like(dj)
            )
            unit[i][j] = v / dj
    return sum((jnp.log(p) for p in pivots[1:]), jnp.log(pivots[0]))


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


# ----------------------------------------------------------------------------- PCM (grid search)


def _inv_quad(x, P):
    """``x^T P^{-1} x`` for ``x (..., d)``, ``P (..., d, d)``: closed form for ``d <= 2`` (gmjax's formulas)."""
    d = P.shape[-1]
    if d == 1:
        return x[..., 0] ** 2 / P[..., 0, 0]
    if d == 2:
        a, b, e = P[..., 0, 0], P[..., 0, 1], P[..., 1, 1]
        x0, x1 = x[..., 0], x[..., 1]
        return (e * x0 * x0 - 2.0 * b * x0 * x1 + a * x1 * x1) / (a * e - b * b)
    L = _chol(P)
    if d > 4:
        r = solve_triangular(L, x[..., None], lower=True)[..., 0]
        return jnp.sum(r * r, -1)
    x = jnp.broadcast_to(x, jnp.broadcast_shapes(x.shape, L.shape[:-1]))
    rs = []  # forward substitution, unrolled and broadcast (a batched solve_triangular calls LAPACK per matrix)
    for i in range(d):
        rs.append(
            (x[..., i] - sum((L[..., i, k] * rs[k] for k in range(i)), jnp.zeros_like(x[..., i])))
            / L[..., i, i]
        )
    return sum(r * r for r in rs)


def _logpdf(x, m, P):
    """``log N(x; m, P)`` broadcast over leading axes."""
    d = P.shape[-1]
    if d == 1:
        logdet = jnp.log(P[..., 0, 0])
    elif d == 2:
        logdet = jnp.log(P[..., 0, 0] * P[..., 1, 1] - P[..., 0, 1] * P[..., 1, 0])
    else:
        logdet = _logdet(P)
    return -0.5 * (d * _LOG_2PI + logdet + _inv_quad(x - m, P))


def _inv(P):
    """Inverse of SPD ``P (..., d, d)``: closed form for ``d <= 2``, Cholesky above."""
    d = P.shape[-1]
    if d == 1:
        return 1.0 / P
    if d == 2:
        a, b, c, e = P[..., 0, 0], P[..., 0, 1], P[..., 1, 0], P[..., 1, 1]
        out = (
            jnp.stack([jnp.stack([e, -b], -1), jnp.stack([-c, a], -1)], -2) / (a * e - b * c)[..., None, None]
        )
        return 0.5 * (out + jnp.swapaxes(out, -1, -2))
    L = _chol(P)
    if d > 4:
        Linv = solve_triangular(L, jnp.broadcast_to(jnp.eye(d, dtype=P.dtype), P.shape), lower=True)
    else:  # L^{-1} unrolled
        zero = jnp.zeros_like(L[..., 0, 0])
        inv = [[zero] * d for _ in range(d)]
        for i in range(d):
            inv[i][i] = 1.0 / L[..., i, i]
            for j in range(i):
                inv[i][j] = -sum((L[..., i, k] * inv[k][j] for k in range(j, i)), zero) * inv[i][i]
        Linv = jnp.stack([jnp.stack(row, -1) for row in inv], -2)
    return jnp.swapaxes(Linv, -1, -2) @ Linv


def _cluster(delta, dist, radii):
    """Gauss clustering (seed 000 eqs 24–28) at every scope of ``radii (G,)``: ``(G, k)`` ``uint32``
    rows (``k <= 32``), bit ``m`` of row ``c`` set when component ``m`` is in the cluster headed by
    slot ``c``.

    Row ``i`` holds the ``j`` with ``δ_ij <= radius`` (eqs 24–25); a row equal to a lower non-empty
    row is emptied (Step 1); then the pairs ``(i, j)``, ``i < j``, are visited in lexicographic order
    and each pair that shares a component is split (Steps 2–3; the other pairs are no-ops):
    identical -> ``j`` emptied; one inside the other -> the subset kept, the superset keeps its
    complement; partial overlap -> every shared component goes to the cluster whose nearest remaining
    member is closer (eq 28, ties to ``i``). One loop walks the grid points one after the other and
    visits only the sharing pairs, so under ``vmap`` it runs the batch's largest *total* number of
    splits, not the sum over the grid of each point's largest.
    """
    k = delta.shape[0]
    ar = jnp.arange(k, dtype=jnp.uint32)
    bit = jnp.left_shift(jnp.uint32(1), ar)
    rows = jnp.sum(jnp.where(delta[None] <= radii[:, None, None], bit, jnp.uint32(0)), -1, dtype=jnp.uint32)
    lower = ar[None, :] < ar[:, None]
    dup = jnp.any((rows[:, :, None] == rows[:, None, :]) & lower & (rows[:, None, :] != 0), -1)
    rows = jnp.where(dup, jnp.uint32(0), rows)

    def members(row):
        return (jnp.right_shift(row, ar) & 1) == 1

    def next_pair(rows, i, j):  # the first sharing pair (i', j') >= (i, j), i' < j'
        in_row = ((rows & rows[i]) != 0) & (ar >= j) & (ar > i)
        later = jnp.append(jax.lax.associative_scan(jnp.bitwise_or, rows, reverse=True)[1:], jnp.uint32(0))
        has = ((rows & later) != 0) & (ar > i)  # rows after i sharing with a row after them
        here = jnp.any(in_row)
        i2 = jnp.where(here, i, jnp.argmax(has).astype(jnp.uint32))
        j2 = jnp.argmax(jnp.where(here, in_row, ((rows & rows[i2]) != 0) & (ar > i2))).astype(jnp.uint32)
        return here | jnp.any(has), i2, j2

    def split(rows, i, j):
        ci, cj = rows[i], rows[j]
        ov, ri, rj = ci & cj, ci & ~cj, cj & ~ci
        di = jnp.min(jnp.where(members(ri)[:, None], dist, jnp.inf), 0)
        dj = jnp.min(jnp.where(members(rj)[:, None], dist, jnp.inf), 0)
        to_i = ov & jnp.sum(jnp.where(di <= dj, bit, jnp.uint32(0)), dtype=jnp.uint32)
        j_in_i, i_in_j = rj == 0, ri == 0
        new_i = jnp.where(j_in_i & i_in_j, ci, jnp.where(j_in_i, ri, jnp.where(i_in_j, ci, ri | to_i)))
        new_j = jnp.where(j_in_i & i_in_j, 0, jnp.where(j_in_i, cj, jnp.where(i_in_j, rj, rj | (ov & ~to_i))))
        return jnp.where(ar == i, new_i, jnp.where(ar == j, new_j, rows))

    def step(carry):  # split the next sharing pair of grid point g, or move on to g + 1
        rows_all, g, i, j = carry
        rows = rows_all[g]
        found, i, j = next_pair(rows, i, j)
        rows_all = rows_all.at[g].set(jnp.where(found, split(rows, i, j), rows))
        return rows_all, jnp.where(found, g, g + 1), jnp.where(found, i, 0), jnp.where(found, j + 1, 1)

    zero = jnp.zeros((), jnp.uint32)
    return jax.lax.while_loop(lambda c: c[1] < radii.shape[0], step, (rows, zero, zero, zero + 1))[0]


def _pcm(log_w, m, P, k: int, rho, alpha, lambda_range, grid_size: int, range_scale, dims):
    """Seed 000 PCM-GMR with the grid confidence search (no Newton), as ``gmjax.reduction.PCM(
    max_components=k, capacity=k, newton_steps=0)``: censored pruning to the ``N <= k`` heaviest
    holding ``rho`` of the mass (eqs 19–22; eq 41 rescales them to the input's total), Gauss clustering at
    every ``λ`` of the grid (eqs 23–28), covariance-intersection merge (eqs 38–39) and EISE (eqs 29–35);
    the first grid minimiser is kept. Output slot ``c`` is the cluster headed by pruned slot ``c``
    (dead slots copy cluster 0, which is never empty).

    The λ-independent parts (similarity thresholds, centre distances, inverse covariances and the
    pairwise overlaps ``∫ N_m N_n``) are computed once; the cross term ``∫ f_c q_c`` only at each
    component's own cluster (the other terms of gmjax's ``(K, C)`` matrix are multiplied by 0).
    """
    dtype = m.dtype
    d = m.shape[-1]
    # censored pruning (eqs 19-22, 41): heaviest first, ties to the lower slot
    w_all = jnp.exp(log_w)
    total = jnp.sum(w_all)
    w, idx = jax.lax.top_k(w_all, k)
    n_keep = jnp.minimum(1 + jnp.sum(jnp.cumsum(w) < rho * total), k)
    live = jnp.arange(k) < n_keep
    w = jnp.where(live, w, 0.0)
    w = w * (total / jnp.sum(w))
    m, P = m[idx], P[idx]
    # lambda-independent pieces
    cm, cP = (m, P) if dims is None else (m[:, dims], P[:, dims][:, :, dims])
    maha = _inv_quad(cm[None, :, :] - cm[:, None, :], cP[:, None])  # [i, j]: (u_j - u_i)' P_i^-1 (u_j - u_i)
    sq = jnp.maximum(maha, maha.T)
    live2 = live[:, None] & live[None, :]
    delta = jnp.where(live2, jnp.sqrt(jnp.where(sq > 0, sq, 0.0)), jnp.inf)
    delta = jnp.where(jnp.eye(k, dtype=bool) & live2, 0.0, delta)
    diff = cm[:, None, :] - cm[None, :, :]
    sqd = jnp.sum(diff * diff, -1)
    dist = jnp.where(sqd > 0, jnp.sqrt(jnp.where(sqd > 0, sqd, 1.0)), 0.0)
    info = jnp.where(live[:, None, None], _inv(P), 0.0)
    ww_S = jnp.where(live2, jnp.exp(_logpdf(m[:, None], m[None], P[:, None] + P[None])), 0.0) * jnp.outer(
        w, w
    )
    eye = jnp.eye(d, dtype=dtype)
    ar = jnp.arange(k, dtype=jnp.uint32)
    lo, hi = (jnp.asarray(v, dtype) for v in lambda_range)
    grid = lo + (hi - lo) * jnp.linspace(0.0, 1.0, grid_size, dtype=dtype)

    def evaluate(rows):
        A = ((jnp.right_shift(rows[None, :], ar[:, None]) & 1) == 1).astype(dtype)  # (k, C) one-hot
        omega = A * w[:, None]
        W = jnp.sum(omega, 0)
        on = W > 0
        frac = omega / jnp.where(on, W, 1.0)[None, :]
        cov = _inv(jnp.where(on[:, None, None], jnp.einsum("kc,kij->cij", frac, info), eye))
        mu = jnp.einsum("cij,cj->ci", cov, jnp.einsum("kc,kij,kj->ci", frac, info, m))
        mu, cov = jnp.where(on[:, None], mu, 0.0), jnp.where(on[:, None, None], cov, eye)
        # per-cluster ISE (eqs 31, 35): J_hh - 2 J_hr + J_rr, clipped at 0
        own = jnp.argmax(A, 1)
        cross = jnp.where(live, jnp.exp(_logpdf(m, mu[own], P + cov[own])), 0.0) * w
        j_hh = jnp.einsum("mc,mn,nc->c", A, ww_S, A)
        j_hr = (A.T @ cross) * W
        j_rr = W * W * jnp.exp(_logpdf(mu, mu, 2.0 * cov))
        ise = jnp.maximum(jnp.where(on, j_hh - 2.0 * j_hr + j_rr, 0.0), 0.0)
        value = 0.5 * jnp.sum(ise) + alpha * jnp.exp(jnp.sum(on).astype(dtype) / n_keep.astype(dtype))
        return value, W, mu, cov

    values, W, mu, cov = jax.vmap(evaluate)(_cluster(delta, dist, range_scale * grid))
    best = jnp.argmin(values)
    W, mu, cov = W[best], mu[best], cov[best]
    on = W > 0
    mu = jnp.where(on[:, None], mu, mu[0])
    cov = jnp.where(on[:, None, None], 0.5 * (cov + jnp.swapaxes(cov, -1, -2)), cov[0])
    return jnp.where(on, jnp.log(jnp.where(on, W, 1.0)), -jnp.inf), mu, cov


def minimal_gsf(
    f: Callable,
    h: Callable,
    prior: Mix,
    q: Mix,
    r: Mix,
    capacity: int,
    reducer: str = "prune",
    *,
    rho: float = 0.9544,
    alpha: float = 1e-3,
    lambda_range: tuple[float, float] = (1.0, 3.0),
    grid_size: int = 11,
    range_scale: float = 0.5,
    dims: tuple[int, ...] | None = None,
) -> Callable[[jax.Array, jax.Array], tuple[jax.Array, jax.Array]]:
    """``run(zs (T, mz), ts (T,)) -> (means (T, d), covs (T, d, d))`` of an EKF-based GSF.

    Args:
        f, h: ``f(x (d,), t)``, ``h(x (d,), t)``.
        prior, q, r: ``(log_w, means, covs)`` of the prior (padded to ``capacity`` with ``-inf`` log
            weights), the process noise and the measurement noise (normalised log weights).
        capacity: ``K``, the posterior's slots.
        reducer: ``"prune"`` (keep the ``K`` heaviest), ``"runnalls"`` or ``"pcm"`` (PCM-GMR with the
            grid confidence search, ``N_u = K``).
        rho, alpha, lambda_range, grid_size, range_scale, dims: PCM's parameters (as
            ``gmjax.reduction.PCM``; defaults of the seed 000 studies).
    """
    F, H = jax.jacfwd(f), jax.jacfwd(h)
    if reducer == "pcm":
        if capacity > 32:
            raise ValueError(
                f"capacity: the minimal PCM keeps clusters as uint32 bitmasks (<= 32), got {capacity}"
            )
        cfg = (rho, alpha, lambda_range, grid_size, range_scale, None if dims is None else list(dims))

        def reduce(log_w, m, P, k):
            return _pcm(log_w, m, P, k, *cfg)
    else:
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
