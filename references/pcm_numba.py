"""Prune-cluster-merge (PCM, seed 000) with the grid search of ``λ`` as a compiled per-mixture loop
(numba): the speed limit for ``gmjax.reduction.pcm(gm, newton_steps=0)``.

What a user who wants PCM fast without JAX would write: one plain loop per mixture, compiled with
numba's ``@njit``, and a batch driver that runs the mixtures in parallel with ``numba.prange``
(``parallel=True``). It mirrors ``gmjax.reduction.pcm`` with ``newton_steps=0``, ``mode="hard"``,
``merge="ci"``, ``prune=True`` (``gmjax/reduction/pcm.py`` ``_pcm_core``, the grid branch of
``eise/search.py``, ``clustering.py``, ``eise/ise.py``, ``merge.py``, ``_util.finalize``), i.e. seed
000 Table 1 steps 2-6 with step 7's search of the confidence multiplier done on a grid:

1. **Weight-censored pruning** (eqs 19-22): the live weights sorted descending, ``N`` = the smallest
   count whose heaviest components hold at least ``ρ`` of the total (eqs 20-21: ``I - n_max + 1``),
   capped by ``N_u`` = ``max_components`` (eq 22); the survivors, heaviest first (ties: the lower
   slot), rescaled to the input's total weight (eq 41, read as dividing by the *removed* mass as
   gmjax does) into a working mixture of ``N`` components.
2. **Gauss clustering at** ``σ* = λσ`` (eqs 23-28) for every ``λ`` of the grid
   ``lo + (hi - lo) · linspace(0, 1, G)`` (§IV-A scope ``[1, 3]``, ``G = 11``): the judgment matrix
   ``r_ij = [δ_ij <= s λ]`` (eq 24 in gmjax's reading: ``δ_ij`` the larger of the two Mahalanobis
   distances on the clustering dimensions ``dims``, §IV-D; ``s`` = ``range_scale`` = 0.5), clusters =
   its rows (eq 25) as bit rows of ``uint64`` words; identical rows combined (Step 1, the lowest
   index kept); every pair ``i < j`` visited once in lexicographic order (Steps 2-3): a subset is kept
   whole and the superset keeps its complement (Situation 3, ``"split"``), identical clusters are
   combined, and in a partial overlap (Situation 2) the shared components are removed (eq 27) and
   each re-assigned to the renewed cluster with the nearer member centre (eq 28, Euclidean on
   ``dims``; a tie to ``i``). A cluster is labelled by its head row.
3. **Covariance-intersection merge** of every cluster with its normalised weights (eqs 38-39, the
   weights of eq 41): ``P̄^{-1} = Σ (w_m / W) P_m^{-1}``, ``ū = P̄ Σ (w_m / W) P_m^{-1} u_m``, weight
   ``W = Σ w_m``.
4. **EISE** (eq 29 with eqs 31, 35): ``½ Σ_c max(J_hh - 2 J_hr + J_rr, 0) + α e^{N'/N}``; the
   chosen ``λ`` is the first grid point of least EISE (``jnp.argmin``).

Output as gmjax's: ``capacity`` slots (default ``K``), the clusters in increasing head order (or,
if more clusters than ``capacity``, the heaviest, heaviest first, not renormalised: ``overflow``),
padding ``(0, 0, I)`` with ``mask`` False; ``labels`` ``(K,)`` the output slot of every input slot
(``-1`` for pruned and padded slots); ``lam`` ``λ*`` and ``eise`` its EISE (gmjax's
``info.aux["lambda"]`` and ``info.cost``).

What makes it the strong loop rather than the naive one: everything that does not depend on ``λ``
is computed once per mixture (the ``δ_ij`` and centre distances, each ``P_m^{-1}`` and
``P_m^{-1} u_m``, the ``J_hh`` overlaps ``N(u_m; u_n, P_m + P_n)`` of every pair); with
``skip_repeats`` (default) a grid point whose judgment matrix has as many entries as the previous
one's has the same clustering (the matrix only grows with ``λ``) and is not clustered again, and one
whose clustering is the same partition as the last one costed is not merged or costed again; a
singleton cluster is the component itself with an integral of exactly 0 (gmjax inverts twice and
clips the rounding to 0). ``skip_repeats=False`` costs every grid point; the results are the same to
the bit. All arithmetic in float64; log-determinants, inverses and quadratic forms by gmjax's closed
forms for ``d <= 2`` and its Cholesky elimination above (``reduction_numba``'s helpers), so outputs
equal gmjax to rounding (sums are taken in slot order, XLA's in its own).

**Ties.** The same partition can come out of two grid points under different head rows (so in
another output order). Its EISE is then one number, and which grid point wins is a matter of
rounding: gmjax sums the clusters in head order (it keeps the first point within ``K eps`` of the
minimum; until 620bbd7 its ``argmin`` could take the later point, differently under ``vmap`` than
for one mixture). Here each cluster's sums run over its
members in slot order and the clusters are summed in the order of their lowest members, so a
partition's EISE does not depend on its heads and the first grid point is kept: the choice exact
arithmetic makes. Should the two still differ, the mixture has another ``λ*``, output order and
labels than gmjax's, with the same EISE, partition and mixture (``tests/reduction/test_pcm_numba.py`` checks exactly that).

Omitted: Newton's steps on the relaxed EISE (``newton_steps > 0``, the default of ``gmjax.pcm``),
the relaxed modes (``"soft"``, ``"straight_through"``), a fixed ``lam``, the moment merge,
``prune=False``, NaN thresholds, float32, and mixtures without a live component or with zero
weights (gmjax's search and final merge then treat a zero-weight cluster differently).

Without numba the module still imports and runs as plain Python (``njit`` is the identity, ``prange``
is ``range``); with numba each public function's ``.py_func`` is the same code run by the Python
interpreter, which is what the default tests use. This module does not import gmjax.
"""

from __future__ import annotations

import math

import numpy as np

from references.reduction_numba import HAVE_NUMBA, _cholesky_at, _inv_at, _logdet_quad

if HAVE_NUMBA:  # pragma: no cover - exercised with and without numba
    from numba import njit, prange
    from numba.extending import register_jitable
else:  # pragma: no cover
    from references.reduction_numba import njit, prange, register_jitable

__all__ = ["HAVE_NUMBA", "pcm", "pcm_batch"]

_LOG_2PI = 1.8378770664093453
_JIT = {"error_model": "numpy"}  # inf / nan on division by zero, no Python exception checks
_BITS = 64
_BIT = np.array([1 << b for b in range(_BITS)], dtype=np.uint64)  # a compile-time constant
_ZERO = np.uint64(0)


# ----------------------------------------------------------------------------- λ-independent parts


@register_jitable
def _prune(w_in, mask, rho, max_components, ww, wm, wP, m_in, P_in, src):
    """Seed 000 eqs 19-22, 41: the ``N`` survivors, heaviest first, into ``ww, wm, wP`` (scaled to
    the input's total); ``src[r]`` = input slot of survivor ``r``. Returns ``N``."""
    K, d = m_in.shape
    key = np.empty(K)
    total = 0.0
    n_live = 0
    for k in range(K):
        if mask[k]:
            key[k] = -w_in[k]
            total += w_in[k]
            n_live += 1
        else:
            key[k] = np.inf
    order = np.argsort(key, kind="mergesort")  # descending weights, ties to the lower slot
    m_star = 1
    csum = 0.0
    for r in range(n_live):  # eqs 20-21: 1 + #{r: the r + 1 heaviest hold less than ρ}
        csum += w_in[order[r]]
        if csum < rho * total:
            m_star += 1
    n = min(m_star, n_live)
    if max_components >= 0:
        n = min(n, max_components)  # eq 22
    kept = 0.0
    for r in range(n):
        kept += w_in[order[r]]
    scale = total / kept if kept > 0 else 1.0  # eq 41
    for r in range(n):
        k = order[r]
        src[r] = k
        ww[r] = w_in[k] * scale
        for a in range(d):
            wm[r, a] = m_in[k, a]
            for b in range(d):
                wP[r, a, b] = P_in[k, a, b]
    return n


@register_jitable
def _thresholds(n, wm, wP, dims, delta, dist, C, Lc):
    """``δ_ij`` (the larger Mahalanobis distance of the two centres on ``dims``, 0 on the diagonal;
    gmjax's ``similarity_thresholds``) and the Euclidean centre distances on ``dims`` (eq 23)."""
    dc = dims.shape[0]
    for i in range(n):  # the clustering covariances P_i[dims, dims] (and their Cholesky factors)
        for a in range(dc):
            for b in range(dc):
                C[i, a, b] = wP[i, dims[a], dims[b]]
        if dc > 2:
            _cholesky_at(C, i, Lc[i])
    r = np.empty(dc)
    for i in range(n):  # delta[i, j] holds (u_j - u_i)^T C_i^{-1} (u_j - u_i) for now
        for j in range(n):
            if i == j:
                delta[i, j] = 0.0
                continue
            if dc == 1:
                x0 = wm[j, dims[0]] - wm[i, dims[0]]
                q = x0 * x0 / C[i, 0, 0]
            elif dc == 2:
                a, b, e = C[i, 0, 0], C[i, 0, 1], C[i, 1, 1]
                x0 = wm[j, dims[0]] - wm[i, dims[0]]
                x1 = wm[j, dims[1]] - wm[i, dims[1]]
                q = (e * x0 * x0 - 2.0 * b * x0 * x1 + a * x1 * x1) / (a * e - b * b)
            else:
                q = 0.0
                for p in range(dc):
                    acc = wm[j, dims[p]] - wm[i, dims[p]]
                    for t in range(p):
                        acc -= Lc[i, p, t] * r[t]
                    r[p] = acc / Lc[i, p, p]
                    q += r[p] * r[p]
            delta[i, j] = q
    for i in range(n):
        for j in range(i + 1, n):
            s = max(delta[i, j], delta[j, i])
            s = math.sqrt(s) if s > 0 else 0.0
            delta[i, j] = s
            delta[j, i] = s
        for j in range(n):
            s = 0.0
            for p in range(dc):
                x = wm[i, dims[p]] - wm[j, dims[p]]
                s += x * x
            dist[i, j] = math.sqrt(s) if s > 0 else 0.0


@register_jitable
def _log_overlap(m1, i, P1, m2, j, P2, c2, S, x, L, r):
    """``log N(m1[i]; m2[j], P1[i] + c2 P2[j])`` (gmjax's ``spd_logpdf``: closed forms for ``d <= 2``,
    the Cholesky elimination above, ``S``, ``x``, ``L``, ``r`` scratch)."""
    d = m1.shape[1]
    if d == 1:
        v = P1[i, 0, 0] + c2 * P2[j, 0, 0]
        x0 = m1[i, 0] - m2[j, 0]
        return -0.5 * (_LOG_2PI + math.log(v) + x0 * x0 / v)
    if d == 2:
        a = P1[i, 0, 0] + c2 * P2[j, 0, 0]
        b = P1[i, 0, 1] + c2 * P2[j, 0, 1]
        c = P1[i, 1, 0] + c2 * P2[j, 1, 0]
        e = P1[i, 1, 1] + c2 * P2[j, 1, 1]
        x0 = m1[i, 0] - m2[j, 0]
        x1 = m1[i, 1] - m2[j, 1]
        ld = math.log(a * e - b * c)
        q = (e * x0 * x0 - 2.0 * b * x0 * x1 + a * x1 * x1) / (a * e - b * b)
        return -0.5 * (2.0 * _LOG_2PI + ld + q)
    for p in range(d):
        x[p] = m1[i, p] - m2[j, p]
        for t in range(d):
            S[0, p, t] = P1[i, p, t] + c2 * P2[j, p, t]
    ld, q = _logdet_quad(S, x, L, r)
    return -0.5 * (d * _LOG_2PI + ld + q)


# ----------------------------------------------------------------------------- clustering


@register_jitable
def _has(rows, c, m):
    return (rows[c, m // _BITS] & _BIT[m % _BITS]) != _ZERO


@register_jitable
def _cluster(n, delta, radius, dist, rows, labels, members):
    """Seed 000 eqs 24-28 at scope ``radius`` = ``s λ`` into the bit rows ``rows`` ``(n, W)``
    (clusters by head row) and ``labels`` ``(n,)`` (head of each component); ``members`` ``(3, n)``
    scratch."""
    nw = rows.shape[1]
    for i in range(n):  # eqs 24-25: cluster i = row i of the judgment matrix
        for q in range(nw):
            rows[i, q] = _ZERO
        for j in range(n):
            if delta[i, j] <= radius:
                rows[i, j // _BITS] |= _BIT[j % _BITS]
    for i in range(n):  # Step 1: a row equal to a lower non-empty row is emptied
        for j in range(i):
            same = True
            empty = True
            for q in range(nw):
                same = same and rows[i, q] == rows[j, q]
                empty = empty and rows[j, q] == _ZERO
            if same and not empty:
                for q in range(nw):
                    rows[i, q] = _ZERO
                break
    for i in range(n):  # Steps 2-3: every pair once, lexicographic, in the current state
        for j in range(i + 1, n):
            share = False
            j_in_i = True
            i_in_j = True
            for q in range(nw):
                ci = rows[i, q]
                cj = rows[j, q]
                share = share or (ci & cj) != _ZERO
                j_in_i = j_in_i and (cj & ~ci) == _ZERO
                i_in_j = i_in_j and (ci & ~cj) == _ZERO
            if not share:  # Situation 1
                continue
            if j_in_i and i_in_j:  # identical: combined into C_i
                for q in range(nw):
                    rows[j, q] = _ZERO
            elif j_in_i:  # Situation 3: the subset C_j whole, C_i keeps its complement
                for q in range(nw):
                    rows[i, q] = rows[i, q] & ~rows[j, q]
            elif i_in_j:
                for q in range(nw):
                    rows[j, q] = rows[j, q] & ~rows[i, q]
            else:  # Situation 2: eq 27, then eq 28 against the renewed clusters (ties to i)
                n_ov = 0
                n_i = 0
                n_j = 0
                for m in range(n):
                    in_i = _has(rows, i, m)
                    in_j = _has(rows, j, m)
                    if in_i and in_j:
                        members[0, n_ov] = m
                        n_ov += 1
                    elif in_i:
                        members[1, n_i] = m
                        n_i += 1
                    elif in_j:
                        members[2, n_j] = m
                        n_j += 1
                for k in range(n_ov):  # all at once: the renewed clusters are the lists above
                    m = members[0, k]
                    di = np.inf
                    for t in range(n_i):
                        di = min(di, dist[members[1, t], m])
                    dj = np.inf
                    for t in range(n_j):
                        dj = min(dj, dist[members[2, t], m])
                    q, bit = m // _BITS, _BIT[m % _BITS]
                    if di <= dj:
                        rows[j, q] = rows[j, q] & ~bit
                    else:
                        rows[i, q] = rows[i, q] & ~bit
    for c in range(n):
        for m in range(n):
            if _has(rows, c, m):
                labels[m] = c


# ----------------------------------------------------------------------------- merge and EISE


@register_jitable
def _merge_and_eise(n, labels, ww, wm, wP, info, eta, S_hh, alpha, cw, cm, cP, count, scratch):
    """CI merge of every cluster (eqs 38-39) into slot ``head`` of ``cw, cm, cP`` (``count[c]``
    members; 0 for a row that heads no cluster) and the EISE (eq 29 with eqs 31, 35). Returns
    ``(eise, N')``.

    Every cluster's sums run over its members in slot order and the clusters' integrals are summed
    in the order of their lowest members: the EISE of a partition does not depend on which rows head
    its clusters, so two grid points with the same partition have the same EISE to the bit.
    """
    d = wm.shape[1]
    S, Si, x, L, Li, r, perv = scratch
    for c in range(n):
        cw[c] = 0.0
        count[c] = 0
        perv[c] = 0.0
    for m in range(n):  # a cluster's members may sit on either side of its head row
        cw[labels[m]] += ww[m]
        count[labels[m]] += 1
    n_out = 0
    ise = 0.0
    for c in range(n):
        if count[c] == 0:
            continue
        n_out += 1
        W = cw[c]
        if count[c] == 1:  # the component itself; its integral is exactly 0
            for m in range(n):
                if labels[m] == c:
                    for a in range(d):
                        cm[c, a] = wm[m, a]
                        for b in range(d):
                            cP[c, a, b] = wP[m, a, b]
            continue
        for a in range(d):
            x[a] = 0.0
            for b in range(d):
                Si[0, a, b] = 0.0
        for m in range(n):
            if labels[m] == c:
                f = ww[m] / W
                for a in range(d):
                    x[a] += f * eta[m, a]
                    for b in range(d):
                        Si[0, a, b] += f * info[m, a, b]
        _inv_at(Si, 0, cP, c, L, Li)  # P̄ (eq 38)
        for a in range(d):
            s = 0.0
            for b in range(d):
                s += cP[c, a, b] * x[b]
            cm[c, a] = s  # ū (eq 39)
        # eq 35: J_hh over the member pairs, J_hr member against merge, J_rr
        j_hh = 0.0
        cross = 0.0
        for m in range(n):
            if labels[m] != c:
                continue
            row = 0.0
            for k in range(n):
                if labels[k] == c:
                    row += S_hh[m, k] * ww[k]
            j_hh += ww[m] * row
            cross += ww[m] * math.exp(_log_overlap(wm, m, wP, cm, c, cP, 1.0, S, x, L, r))
        self_norm = math.exp(_log_overlap(cm, c, cP, cm, c, cP, 1.0, S, x, L, r))
        per = j_hh - 2.0 * cross * W + W * W * self_norm
        for m in range(n):  # stored at the cluster's lowest member
            if labels[m] == c:
                perv[m] = per if per > 0 else 0.0
                break
    for m in range(n):
        ise += perv[m]
    return 0.5 * ise + alpha * math.exp(n_out / n), n_out


# ----------------------------------------------------------------------------- one mixture


@register_jitable
def _pcm_core(
    w_in,
    m_in,
    P_in,
    mask,
    dims,
    rho,
    max_components,
    alpha,
    lam_lo,
    lam_hi,
    grid_size,
    range_scale,
    skip_repeats,
    out_w,
    out_m,
    out_P,
    out_mask,
    out_labels,
):
    """PCM (grid) of one padded mixture into the ``out_*`` buffers; returns ``(λ*, EISE, N',
    overflow)``."""
    K, d = m_in.shape
    Kw = K if max_components < 0 else min(K, max_components)
    ww, wm, wP = np.zeros(Kw), np.zeros((Kw, d)), np.zeros((Kw, d, d))
    src = np.full(Kw, -1, np.int64)
    n = _prune(w_in, mask, rho, max_components, ww, wm, wP, m_in, P_in, src)
    cap = out_w.shape[0]
    for p in range(cap):
        out_w[p] = 0.0
        out_mask[p] = False
        for a in range(d):
            out_m[p, a] = 0.0
            for b in range(d):
                out_P[p, a, b] = 1.0 if a == b else 0.0
    for k in range(K):
        out_labels[k] = -1
    if n == 0:
        return np.nan, np.nan, 0, False

    # λ-independent parts
    dc = dims.shape[0]
    delta, dist = np.empty((n, n)), np.empty((n, n))
    _thresholds(n, wm, wP, dims, delta, dist, np.empty((n, dc, dc)), np.zeros((n, dc, dc)))
    S, Si = np.zeros((1, d, d)), np.zeros((1, d, d))
    x, r = np.zeros(d), np.zeros(d)
    L, Li = np.zeros((d, d)), np.zeros((d, d))
    scratch = (S, Si, x, L, Li, r, np.zeros(n))
    info, eta = np.empty((n, d, d)), np.empty((n, d))
    for m in range(n):
        _inv_at(wP, m, info, m, L, Li)
        for a in range(d):
            s = 0.0
            for b in range(d):
                s += info[m, a, b] * wm[m, b]
            eta[m, a] = s
    S_hh = np.empty((n, n))  # N(u_m; u_k, P_m + P_k), symmetric
    for m in range(n):
        for k in range(m, n):
            v = math.exp(_log_overlap(wm, m, wP, wm, k, wP, 1.0, S, x, L, r))
            S_hh[m, k] = v
            S_hh[k, m] = v

    # the grid (gmjax: lo + (hi - lo) * linspace(0, 1, G), the first least EISE)
    rows = np.zeros((n, (n + _BITS - 1) // _BITS), np.uint64)
    labels, best_labels = np.zeros(n, np.int64), np.zeros(n, np.int64)
    members = np.zeros((3, n), np.int64)
    cw, cm, cP = np.zeros(n), np.zeros((n, d)), np.zeros((n, d, d))
    bw, bm, bP = np.zeros(n), np.zeros((n, d)), np.zeros((n, d, d))
    count, best_count = np.zeros(n, np.int64), np.zeros(n, np.int64)
    step = 1.0 / (grid_size - 1)
    best_e = np.inf
    best_lam = np.nan
    best_n = 0
    prev_entries = -1
    first, canon, prev_canon = np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n, np.int64)
    have_prev = False
    for g in range(grid_size):
        t = g * step if g < grid_size - 1 else 1.0
        lam = lam_lo + (lam_hi - lam_lo) * t
        radius = range_scale * lam
        if skip_repeats:
            entries = 0
            for i in range(n):
                for j in range(n):
                    if delta[i, j] <= radius:
                        entries += 1
            if entries == prev_entries:  # the same judgment matrix: the same clustering and EISE
                continue
            prev_entries = entries
        _cluster(n, delta, radius, dist, rows, labels, members)
        if skip_repeats:  # the same partition as the last grid point costed (other heads, maybe)
            for c in range(n):
                first[c] = -1
            same = have_prev
            for m in range(n):
                if first[labels[m]] < 0:
                    first[labels[m]] = m
                canon[m] = first[labels[m]]
                same = same and canon[m] == prev_canon[m]
            if same:
                continue
            have_prev = True
            for m in range(n):
                prev_canon[m] = canon[m]
        e, n_out = _merge_and_eise(n, labels, ww, wm, wP, info, eta, S_hh, alpha, cw, cm, cP, count, scratch)
        if e < best_e or best_n == 0:
            best_e, best_lam, best_n = e, lam, n_out
            for c in range(n):
                best_labels[c] = labels[c]
                best_count[c] = count[c]
                bw[c] = cw[c]
                for a in range(d):
                    bm[c, a] = cm[c, a]
                    for b in range(d):
                        bP[c, a, b] = cP[c, a, b]

    # output: clusters by head slot, compacted (gmjax's _util.finalize)
    pos = np.full(n, -1, np.int64)
    overflow = best_n > cap
    if not overflow:
        p = 0
        for c in range(n):
            if best_count[c] > 0:
                pos[c] = p
                p += 1
    else:  # lax.top_k over the cluster weights: descending, ties to the lower head
        taken = np.zeros(n, np.bool_)
        for p in range(cap):
            best = -1
            for c in range(n):
                if best_count[c] > 0 and not taken[c] and (best < 0 or bw[c] > bw[best]):
                    best = c
            taken[best] = True
            pos[best] = p
    for c in range(n):
        p = pos[c]
        if p < 0:
            continue
        out_w[p] = bw[c]
        out_mask[p] = True
        for a in range(d):
            out_m[p, a] = bm[c, a]
            for b in range(d):
                out_P[p, a, b] = bP[c, a, b]
    for s in range(n):
        out_labels[src[s]] = pos[best_labels[s]]
    return best_lam, best_e, best_n, overflow


# ----------------------------------------------------------------------------- public drivers


@njit(**_JIT)
def pcm(
    w,
    m,
    P,
    max_components=-1,
    capacity=-1,
    rho=0.9544,
    alpha=0.001,
    lam_lo=1.0,
    lam_hi=3.0,
    grid_size=11,
    range_scale=0.5,
    dims=None,
    mask=None,
    skip_repeats=True,
):
    """PCM with the grid search of ``λ`` of one padded mixture (``gmjax.reduction.pcm`` with
    ``newton_steps=0``; ``max_components=-1`` / ``capacity=-1`` are gmjax's ``None``).

    Args:
        w, m, P: ``(K,)``, ``(K, d)``, ``(K, d, d)`` float64; mask: ``(K,)`` bool (default all live).
        dims: ``int64`` array of the clustering dimensions (default all, ``np.arange(d)``).
        skip_repeats: reuse the previous grid point's clustering when its judgment matrix is the
            same (identical results; ``False`` evaluates every grid point).

    Returns:
        ``(weights (cap,), means (cap, d), covs (cap, d, d), mask (cap,), labels (K,), lam, eise)``.
    """
    K, d = m.shape
    cap = K if capacity < 0 else capacity
    live = np.ones(K, np.bool_) if mask is None else mask
    cdims = np.arange(d) if dims is None else dims
    ow, om, oP = np.zeros(cap), np.zeros((cap, d)), np.zeros((cap, d, d))
    omask, olab = np.zeros(cap, np.bool_), np.zeros(K, np.int64)
    lam, e, _, _ = _pcm_core(
        w,
        m,
        P,
        live,
        cdims,
        rho,
        max_components,
        alpha,
        lam_lo,
        lam_hi,
        grid_size,
        range_scale,
        skip_repeats,
        ow,
        om,
        oP,
        omask,
        olab,
    )
    return ow, om, oP, omask, olab, lam, e


@njit(parallel=True, **_JIT)
def pcm_batch(
    w,
    m,
    P,
    max_components=-1,
    capacity=-1,
    rho=0.9544,
    alpha=0.001,
    lam_lo=1.0,
    lam_hi=3.0,
    grid_size=11,
    range_scale=0.5,
    dims=None,
    mask=None,
    skip_repeats=True,
):
    """:func:`pcm` over a batch ``(B, K, ...)``, mixtures in parallel (``prange``); the outputs
    gain the leading ``B`` axis (``lam`` and ``eise`` are ``(B,)``)."""
    B, K, d = m.shape
    cap = K if capacity < 0 else capacity
    live = np.ones((B, K), np.bool_) if mask is None else mask
    cdims = np.arange(d) if dims is None else dims
    ow, om, oP = np.zeros((B, cap)), np.zeros((B, cap, d)), np.zeros((B, cap, d, d))
    omask, olab = np.zeros((B, cap), np.bool_), np.zeros((B, K), np.int64)
    lam, e = np.zeros(B), np.zeros(B)
    for b in prange(B):
        lb, eb, _, _ = _pcm_core(
            w[b],
            m[b],
            P[b],
            live[b],
            cdims,
            rho,
            max_components,
            alpha,
            lam_lo,
            lam_hi,
            grid_size,
            range_scale,
            skip_repeats,
            ow[b],
            om[b],
            oP[b],
            omask[b],
            olab[b],
        )
        lam[b] = lb
        e[b] = eb
    return ow, om, oP, omask, olab, lam, e
