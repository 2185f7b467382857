"""Runnalls, West and GMRC as compiled per-mixture loops (numba): the speed limit for gmjax's
expensive reducers.

What a user who wants speed without JAX would write: one plain loop per mixture, compiled with
numba's ``@njit``, and a batch driver that runs the mixtures in parallel with ``numba.prange``
(``parallel=True``). The loops are the fair, strong baseline, not the naive one:

* **Runnalls (2007)**: per-component ``log det P_k`` cached; the pair-cost matrix
  ``B(i, j) = 1/2 [(w_i + w_j) log det P_ij - w_i log det P_i - w_j log det P_j]`` is computed once
  and after a merge only the merged row/column is recomputed (``O(K d^3)`` per merge); every row
  keeps its minimum and first minimiser, so a step selects the pair in ``O(K)`` (a row is rescanned
  only when its minimiser died or grew).
* **West (1993)**: per-component ``log det P_k`` and ``P_k^{-1}`` cached (refreshed only for the
  merged slot); each step scans the weights and one row of ``KL(N_i || N_k)`` (or the ISE of the two
  unit-weight Gaussians), ``O(K d^2)`` per merge. The enhanced variant (Chen, Chang & Smith 2010)
  ranks by ``w / det P``.
* **GMRC (Schieferdecker & Huber 2009)**: Runnalls' loop down to ``num_out`` for the start, then
  k-means with the assignment ``argmin_c KL(N_i || N_c)`` (the centers' inverses and
  log-determinants cached per iteration) and moment-preserving cluster merges, until the labels stop
  changing or ``max_iter``.

Inputs are padded float64 arrays as in gmjax: weights ``(K,)``, means ``(K, d)``, covariances
``(K, d, d)`` and an optional ``mask`` ``(K,)`` (default: every slot live); the batch drivers take a
leading batch axis ``B``. The conventions, merge sequence and output layout are gmjax's
(``gmjax/reduction/_greedy.py``, ``_util.finalize``), so outputs equal ``gmjax.reduction`` to
rounding:

* The pair ``(i, j)`` is merged into slot ``i``, slot ``j`` is emptied to ``(0, 0, I)``. Runnalls:
  ``i < j`` is the first minimiser of the upper triangle in row-major slot order, the cost of a pair
  with the freshly merged slot evaluated with that slot as the first argument (as gmjax's row update).
  West: ``i`` is the first smallest-weight live slot, ``j`` its first nearest neighbour.
* Merging continues while ``n_live > num_out`` and the selected cost is finite and
  ``<= threshold``. ``merges`` is ``(K - num_out, 2)`` in input slot indices, ``-1`` rows after the
  last merge; ``cost`` is the sum of the selected costs (GMRC: ``sum_i w_i KL(N_i || N_c(i))``).
* Output of ``capacity`` slots (default ``K``): the live slots moved to the front in slot order,
  padding ``(0, 0, I)`` with ``mask`` False; ``labels`` ``(K,)`` the output slot of every input slot
  (``-1`` for padded ones). If more than ``capacity`` slots are live (a threshold stopped early),
  the heaviest are kept, heaviest first, not renormalised. Weights are used and returned as stored.
* Log-determinants, inverses and quadratic forms use gmjax's closed forms for ``d <= 2`` and the
  Cholesky elimination in gmjax's order above; log-determinants for ``d > 2`` as gmjax's, the logs
  of the LDL^T pivots summed in pivot order (except Runnalls' pair costs: the log of the product
  of the pivots, one log per pair; equal to rounding).

Without numba the module still imports and runs as plain Python (``njit`` is then the identity and
``prange`` is ``range``); with numba, every public function's ``.py_func`` is the same code run by
the Python interpreter (the helpers are ``register_jitable``: plain functions when called from
Python, compiled when called from compiled code), which is what the default tests use. This module
does not import gmjax.
"""

from __future__ import annotations

import math

import numpy as np

try:  # pragma: no cover - exercised with and without numba
    from numba import njit, prange
    from numba.extending import register_jitable

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False
    prange = range

    def _identity_decorator(*args, **kwargs):
        def wrap(f):
            f.py_func = f
            return f

        if len(args) == 1 and callable(args[0]) and not kwargs:
            return wrap(args[0])
        return wrap

    njit = _identity_decorator
    register_jitable = _identity_decorator


__all__ = [
    "HAVE_NUMBA",
    "runnalls",
    "runnalls_batch",
    "west",
    "west_batch",
    "gmrc",
    "gmrc_batch",
]

_LOG_2PI = 1.8378770664093453
_JIT = {"error_model": "numpy"}  # inf / nan on division by zero, no Python exception checks


# ----------------------------------------------------------------------------- small-matrix algebra
# Helpers read matrices by index (``P[k, a, b]``), never by slicing (``P[k]``, a new array view), and
# the hot loops (a cost row, a KL row, the GMRC assignment) do their per-pair arithmetic inline: a
# per-pair call of a helper with array arguments that the compiler does not inline made the 60 x 60
# cost matrix 4-6x slower (measured), more than the 2x2 arithmetic itself. Scratch matrices for the
# general-d paths are ``(1, d, d)`` arrays used at index 0.


@register_jitable
def _cholesky_at(A, k, L):
    """Lower Cholesky factor of ``A[k]`` ``(d, d)`` into ``L`` (gmjax's unrolled elimination order;
    NaN where a pivot is not positive)."""
    d = L.shape[0]
    for j in range(d):
        s = 0.0
        for q in range(j):
            s += L[j, q] * L[j, q]
        diag = A[k, j, j] - s
        ljj = math.sqrt(diag) if diag > 0 else math.nan
        L[j, j] = ljj
        for i in range(j + 1, d):
            s = 0.0
            for q in range(j):
                s += L[i, q] * L[j, q]
            L[i, j] = (A[k, i, j] - s) / ljj


@register_jitable
def _ldl_logdet_at(A, k, U):
    """``sum_j log D_j`` over the pivots of the ``L D L^T`` elimination of ``A[k]`` (gmjax's
    ``spd_logdet`` for ``3 <= d <= 6``: unit lower factor into ``U``, logs summed in pivot order;
    NaN where a pivot is not positive)."""
    d = U.shape[0]
    s = 0.0
    for j in range(d):
        dj = A[k, j, j]
        for q in range(j):
            dj -= U[j, q] * U[j, q] * U[q, q]
        U[j, j] = dj  # the pivots on U's diagonal
        for i in range(j + 1, d):
            v = A[k, i, j]
            for q in range(j):
                v -= U[i, q] * U[j, q] * U[q, q]
            U[i, j] = v / dj
        s += math.log(dj) if dj > 0 else math.nan
    return s


@register_jitable
def _logdet_at(P, k, L):
    """``log det P[k]`` (gmjax's ``spd_logdet``: closed form for ``d <= 2``, else the ``L D L^T``
    pivots' logs, scratch ``L``)."""
    d = L.shape[0]
    if d == 1:
        return math.log(P[k, 0, 0])
    if d == 2:
        return math.log(P[k, 0, 0] * P[k, 1, 1] - P[k, 0, 1] * P[k, 1, 0])
    return _ldl_logdet_at(P, k, L)


@register_jitable
def _inv_at(P, k, out, o, L, Li):
    """Symmetric inverse of SPD ``P[k]`` into ``out[o]`` (gmjax's ``spd_inv``: closed form for
    ``d <= 2``, else ``L^-T L^-1`` with ``Li`` scratch for ``L^-1``)."""
    d = L.shape[0]
    if d == 1:
        out[o, 0, 0] = 1.0 / P[k, 0, 0]
        return
    if d == 2:
        a, b, c, e = P[k, 0, 0], P[k, 0, 1], P[k, 1, 0], P[k, 1, 1]
        det = a * e - b * c
        out[o, 0, 0] = e / det
        out[o, 1, 1] = a / det
        off = 0.5 * (-b / det + -c / det)
        out[o, 0, 1] = off
        out[o, 1, 0] = off
        return
    _cholesky_at(P, k, L)
    for i in range(d):
        Li[i, i] = 1.0 / L[i, i]
        for j in range(i):
            acc = 0.0
            for q in range(j, i):
                acc += L[i, q] * Li[q, j]
            Li[i, j] = -acc * Li[i, i]
    for a in range(d):
        for b in range(d):
            s = 0.0
            for q in range(max(a, b), d):
                s += Li[q, a] * Li[q, b]
            out[o, a, b] = s


@register_jitable
def _logdet_quad(S, x, L, r):
    """``(log det S[0], x^T S[0]^{-1} x)`` (gmjax's ``spd_logdet`` / ``spd_inv_quad``); ``r`` scratch."""
    d = L.shape[0]
    if d == 1:
        return math.log(S[0, 0, 0]), x[0] * x[0] / S[0, 0, 0]
    if d == 2:
        a, b, e = S[0, 0, 0], S[0, 0, 1], S[0, 1, 1]
        ld = math.log(a * e - b * S[0, 1, 0])
        det = a * e - b * b
        return ld, (e * x[0] * x[0] - 2.0 * b * x[0] * x[1] + a * x[1] * x[1]) / det
    ld = _ldl_logdet_at(S, 0, L)
    _cholesky_at(S, 0, L)
    q = 0.0
    for i in range(d):  # forward substitution L r = x; x^T S^{-1} x = |r|^2
        acc = x[i]
        for k in range(i):
            acc -= L[i, k] * r[k]
        r[i] = acc / L[i, i]
        q += r[i] * r[i]
    return ld, q


@register_jitable
def _kl_at(m1, P1, ld1, i, m2, P2inv, ld2, k):
    """``KL(N(m1[i], P1[i]) || N(m2[k], P2[k]))`` from ``P2inv[k]`` and both log-determinants
    (gmjax's ``spd_kl``)."""
    d = m1.shape[1]
    tr = 0.0
    for a in range(d):
        for b in range(d):
            tr += P2inv[k, a, b] * P1[i, a, b]
    quad = 0.0
    for a in range(d):
        da = m2[k, a] - m1[i, a]
        for b in range(d):
            quad += da * P2inv[k, a, b] * (m2[k, b] - m1[i, b])
    return 0.5 * (tr + quad - d + ld2[k] - ld1[i])


@register_jitable
def _kl_argmin(m1, P1, ld1, i, m2, P2inv, ld2, use, skip):
    """``(k, KL)``: the first ``k`` with ``use[k]``, ``k != skip``, minimising
    ``KL(N(m1[i], P1[i]) || N(m2[k], P2[k]))`` (``k = -1`` if none); the arithmetic of :func:`_kl_at`
    inside the loop (no per-pair call with array arguments)."""
    d = m1.shape[1]
    best = np.inf
    arg = -1
    for k in range(m2.shape[0]):
        if k == skip or not use[k]:
            continue
        tr = 0.0
        for a in range(d):
            for b in range(d):
                tr += P2inv[k, a, b] * P1[i, a, b]
        quad = 0.0
        for a in range(d):
            da = m2[k, a] - m1[i, a]
            for b in range(d):
                quad += da * P2inv[k, a, b] * (m2[k, b] - m1[i, b])
        kl = 0.5 * (tr + quad - d + ld2[k] - ld1[i])
        if kl < best:
            best = kl
            arg = k
    return arg, best


@register_jitable
def _merged_cov(w, m, P, a, b, S):
    """``(W, l_a, l_b)`` and the moment-merged covariance of slots ``a`` and ``b`` into ``S[0]``
    (seed 002 eqs 70-72 with ``l = w / W``; equal ``l`` for a zero total weight), symmetrised."""
    W = w[a] + w[b]
    if W > 0:
        l1 = w[a] / W
        l2 = w[b] / W
    else:
        l1 = 0.5
        l2 = 0.5
    l12 = l1 * l2
    d = m.shape[1]
    for p in range(d):
        dp = m[a, p] - m[b, p]
        for q in range(d):
            S[0, p, q] = l1 * P[a, p, q] + l2 * P[b, p, q] + l12 * dp * (m[a, q] - m[b, q])
    for p in range(d):
        for q in range(p + 1, d):
            v = 0.5 * (S[0, p, q] + S[0, q, p])
            S[0, p, q] = v
            S[0, q, p] = v
    return W, l1, l2


@register_jitable
def _merge_into_slot(i, j, w, m, P, live, labels, S):
    """Merge slot ``j`` into slot ``i`` in place; slot ``j`` becomes ``(0, 0, I)`` and dead."""
    d = m.shape[1]
    W, l1, l2 = _merged_cov(w, m, P, i, j, S)
    for a in range(d):
        m[i, a] = l1 * m[i, a] + l2 * m[j, a]
        for b in range(d):
            P[i, a, b] = S[0, a, b]
    w[i] = W
    w[j] = 0.0
    for a in range(d):
        m[j, a] = 0.0
        for b in range(d):
            P[j, a, b] = 1.0 if a == b else 0.0
    live[j] = False
    for k in range(labels.shape[0]):
        if labels[k] == j:
            labels[k] = i


@register_jitable
def _start(w_in, m_in, P_in, mask):
    """Working copies (padded weights zeroed), identity labels (``-1`` for padded slots), live count."""
    K = w_in.shape[0]
    w = np.empty(K)
    live = np.empty(K, np.bool_)
    labels = np.empty(K, np.int64)
    n_live = 0
    for k in range(K):
        live[k] = mask[k]
        w[k] = w_in[k] if mask[k] else 0.0
        labels[k] = k if mask[k] else -1
        n_live += 1 if mask[k] else 0
    return w, m_in.copy(), P_in.copy(), live, labels, n_live


@register_jitable
def _finalize(w, m, P, live, labels, out_w, out_m, out_P, out_mask, out_labels):
    """gmjax's ``_util.finalize``: live slots to the front in slot order (or, with more live slots
    than ``capacity``, the heaviest first), padding ``(0, 0, I)``; returns ``(overflow, dropped)``."""
    K = w.shape[0]
    cap = out_w.shape[0]
    d = m.shape[1]
    n_live = 0
    for k in range(K):
        n_live += 1 if live[k] else 0
    pos = np.full(K, -1, np.int64)
    src = np.full(cap, -1, np.int64)
    overflow = n_live > cap
    dropped = 0.0
    if not overflow:
        p = 0
        for k in range(K):
            if live[k]:
                src[p] = k
                pos[k] = p
                p += 1
    else:  # lax.top_k over the live weights: descending, ties to the lower slot
        taken = np.zeros(K, np.bool_)
        for p in range(cap):
            best = -1
            for k in range(K):
                if live[k] and not taken[k] and (best < 0 or w[k] > w[best]):
                    best = k
            taken[best] = True
            src[p] = best
            pos[best] = p
        for k in range(K):
            if live[k] and not taken[k]:
                dropped += w[k]
    for p in range(cap):
        k = src[p]
        out_mask[p] = k >= 0
        out_w[p] = w[k] if k >= 0 else 0.0
        for a in range(d):
            out_m[p, a] = m[k, a] if k >= 0 else 0.0
            for b in range(d):
                if k >= 0:
                    out_P[p, a, b] = P[k, a, b]
                else:
                    out_P[p, a, b] = 1.0 if a == b else 0.0
    for k in range(labels.shape[0]):
        out_labels[k] = pos[labels[k]] if labels[k] >= 0 else -1
    return overflow, dropped


# ----------------------------------------------------------------------------- Runnalls


@register_jitable
def _cost_row(i, start, w, m, P, ld, live, C, S):
    """Runnalls' ``B(i, k) = 1/2 [(w_i + w_k) log det P_ik - w_i log det P_i - w_k log det P_k]``
    (Runnalls 2007 eq 21) of slot ``i`` (the first argument, as gmjax's row update) against every
    live slot ``k >= start``, ``k != i``, into ``C[min(i, k), max(i, k)]``.

    The arithmetic of :func:`_merged_cov` and :func:`_logdet_at` written out per ``d`` inside the
    loop (no per-pair call with array arguments); for ``d > 2`` the log-determinant is the log of
    the product of the LDL^T pivots (one log per pair instead of ``d`` logs and square roots).
    """
    K, d = m.shape
    wi = w[i]
    ldi = ld[i]
    if d == 1:
        mi, pi = m[i, 0], P[i, 0, 0]
        for k in range(start, K):
            if k == i or not live[k]:
                continue
            W = wi + w[k]
            if W > 0:
                l1 = wi / W
                l2 = w[k] / W
            else:
                l1 = 0.5
                l2 = 0.5
            dx = mi - m[k, 0]
            x = l1 * pi + l2 * P[k, 0, 0] + l1 * l2 * dx * dx
            c = 0.5 * (W * math.log(x) - wi * ldi - w[k] * ld[k])
            if k > i:
                C[i, k] = c
            else:
                C[k, i] = c
    elif d == 2:
        mi0, mi1 = m[i, 0], m[i, 1]
        pi00, pi01, pi10, pi11 = P[i, 0, 0], P[i, 0, 1], P[i, 1, 0], P[i, 1, 1]
        for k in range(start, K):
            if k == i or not live[k]:
                continue
            W = wi + w[k]
            if W > 0:
                l1 = wi / W
                l2 = w[k] / W
            else:
                l1 = 0.5
                l2 = 0.5
            l12 = l1 * l2
            dx = mi0 - m[k, 0]
            dy = mi1 - m[k, 1]
            x00 = l1 * pi00 + l2 * P[k, 0, 0] + l12 * dx * dx
            x01 = l1 * pi01 + l2 * P[k, 0, 1] + l12 * dx * dy
            x10 = l1 * pi10 + l2 * P[k, 1, 0] + l12 * dy * dx
            x11 = l1 * pi11 + l2 * P[k, 1, 1] + l12 * dy * dy
            o = 0.5 * (x01 + x10)
            c = 0.5 * (W * math.log(x00 * x11 - o * o) - wi * ldi - w[k] * ld[k])
            if k > i:
                C[i, k] = c
            else:
                C[k, i] = c
    else:
        for k in range(start, K):
            if k == i or not live[k]:
                continue
            W = wi + w[k]
            if W > 0:
                l1 = wi / W
                l2 = w[k] / W
            else:
                l1 = 0.5
                l2 = 0.5
            l12 = l1 * l2
            for p in range(d):
                dp = m[i, p] - m[k, p]
                for q in range(d):
                    S[0, p, q] = l1 * P[i, p, q] + l2 * P[k, p, q] + l12 * dp * (m[i, q] - m[k, q])
            for p in range(d):
                for q in range(p + 1, d):
                    v = 0.5 * (S[0, p, q] + S[0, q, p])
                    S[0, p, q] = v
                    S[0, q, p] = v
            # log det as the log of the product of the LDL^T pivots, in place in S: one log per
            # pair (gmjax takes 2 sum log L_jj of the Cholesky factor: equal to rounding)
            det = 1.0
            for jj in range(d):
                for ii in range(jj, d):
                    acc = S[0, ii, jj]
                    for q in range(jj):
                        acc -= S[0, ii, q] * S[0, jj, q] * S[0, q, q]
                    S[0, ii, jj] = acc if ii == jj else acc / S[0, jj, jj]
                det *= S[0, jj, jj] if S[0, jj, jj] > 0 else math.nan
            c = 0.5 * (W * math.log(det) - wi * ldi - w[k] * ld[k])
            if k > i:
                C[i, k] = c
            else:
                C[k, i] = c


@register_jitable
def _rescan(a, C, live, rowmin, rowarg):
    K = C.shape[0]
    best = np.inf
    arg = -1
    if live[a]:
        for b in range(a + 1, K):
            if live[b] and C[a, b] < best:
                best = C[a, b]
                arg = b
    rowmin[a] = best
    rowarg[a] = arg


@register_jitable
def _runnalls_core(
    w_in, m_in, P_in, mask, num_out, threshold, out_w, out_m, out_P, out_mask, out_labels, out_merges
):
    """Runnalls' greedy merging of one padded mixture into the ``out_*`` buffers; returns
    ``(cost, overflow, dropped)``."""
    K, d = m_in.shape
    w, m, P, live, labels, n_live = _start(w_in, m_in, P_in, mask)
    S = np.zeros((1, d, d))
    L = np.zeros((d, d))
    ld = np.zeros(K)
    for k in range(K):
        if live[k]:
            ld[k] = _logdet_at(P, k, L)
    C = np.full((K, K), np.inf)
    for a in range(K):
        if live[a]:
            _cost_row(a, a + 1, w, m, P, ld, live, C, S)
    rowmin = np.full(K, np.inf)  # every row's minimum and first minimiser (written out: no calls)
    rowarg = np.full(K, -1, np.int64)
    for a in range(K):
        for b in range(a + 1, K):
            if C[a, b] < rowmin[a]:
                rowmin[a] = C[a, b]
                rowarg[a] = b
    for s in range(out_merges.shape[0]):
        out_merges[s, 0] = -1
        out_merges[s, 1] = -1
    total = 0.0
    for step in range(out_merges.shape[0]):
        if n_live <= num_out:
            break
        i = -1
        c = np.inf
        for a in range(K):  # first row holding the smallest row minimum
            if rowmin[a] < c:
                c = rowmin[a]
                i = a
        if i < 0 or not (c <= threshold and math.isfinite(c)):
            break
        j = rowarg[i]
        _merge_into_slot(i, j, w, m, P, live, labels, S)
        ld[i] = _logdet_at(P, i, L)
        ld[j] = 0.0
        n_live -= 1
        out_merges[step, 0] = i
        out_merges[step, 1] = j
        total += c
        for k in range(K):  # row and column j die
            C[j, k] = np.inf
            C[k, j] = np.inf
        _cost_row(i, 0, w, m, P, ld, live, C, S)
        rowmin[j] = np.inf
        rowarg[j] = -1
        _rescan(i, C, live, rowmin, rowarg)
        for k in range(j):  # rows above j: column i changed (k < i), column j died
            if k == i or not live[k]:
                continue
            if rowarg[k] == j:
                _rescan(k, C, live, rowmin, rowarg)
            elif k < i:
                v = C[k, i]
                if rowarg[k] == i:
                    if v <= rowmin[k]:
                        rowmin[k] = v
                    else:
                        _rescan(k, C, live, rowmin, rowarg)
                elif v < rowmin[k] or (v == rowmin[k] and i < rowarg[k]):
                    rowmin[k] = v
                    rowarg[k] = i
    overflow, dropped = _finalize(w, m, P, live, labels, out_w, out_m, out_P, out_mask, out_labels)
    return total, overflow, dropped


@njit(**_JIT)
def runnalls(w, m, P, num_out, threshold=np.inf, capacity=-1, mask=None):
    """Runnalls' greedy KL-bound reduction of one padded mixture (Runnalls 2007, eq 21 cost).

    Args:
        w: ``(K,)`` weights; m: ``(K, d)`` means; P: ``(K, d, d)`` covariances (float64).
        num_out: target count; threshold: stop when the smallest cost exceeds it (default ``inf``).
        capacity: output slots (``-1``: ``K``); mask: ``(K,)`` bool live slots (default all).

    Returns:
        ``(w (cap,), m (cap, d), P (cap, d, d), mask (cap,), labels (K,), merges (K - num_out, 2),
        cost)``.
    """
    K, d = m.shape
    cap = K if capacity < 0 else capacity
    live = np.ones(K, np.bool_) if mask is None else mask
    ow, om, oP = np.zeros(cap), np.zeros((cap, d)), np.zeros((cap, d, d))
    omask, olab = np.zeros(cap, np.bool_), np.zeros(K, np.int64)
    merges = np.empty((max(K - num_out, 0), 2), np.int64)
    cost, _, _ = _runnalls_core(w, m, P, live, num_out, threshold, ow, om, oP, omask, olab, merges)
    return ow, om, oP, omask, olab, merges, cost


@njit(parallel=True, **_JIT)
def runnalls_batch(w, m, P, num_out, threshold=np.inf, capacity=-1, mask=None):
    """:func:`runnalls` over a batch ``(B, K, ...)``, mixtures in parallel (``prange``); the
    outputs gain the leading ``B`` axis (``cost`` is ``(B,)``)."""
    B, K, d = m.shape
    cap = K if capacity < 0 else capacity
    live = np.ones((B, K), np.bool_) if mask is None else mask
    ow, om, oP = np.zeros((B, cap)), np.zeros((B, cap, d)), np.zeros((B, cap, d, d))
    omask, olab = np.zeros((B, cap), np.bool_), np.zeros((B, K), np.int64)
    merges = np.empty((B, max(K - num_out, 0), 2), np.int64)
    cost = np.zeros(B)
    for b in prange(B):
        c, _, _ = _runnalls_core(
            w[b], m[b], P[b], live[b], num_out, threshold, ow[b], om[b], oP[b], omask[b], olab[b], merges[b]
        )
        cost[b] = c
    return ow, om, oP, omask, olab, merges, cost


# ----------------------------------------------------------------------------- West


@register_jitable
def _west_cache(k, P, ld, Pinv, ld2, L, Li):
    """Slot ``k``'s ``log det P``, ``P^{-1}`` and ``log det 2P`` (the ISE self term)."""
    d = P.shape[1]
    ld[k] = _logdet_at(P, k, L)
    _inv_at(P, k, Pinv, k, L, Li)
    ld2[k] = ld[k] + d * math.log(2.0)


@register_jitable
def _west_core(
    w_in,
    m_in,
    P_in,
    mask,
    num_out,
    threshold,
    metric_ise,
    enhanced,
    out_w,
    out_m,
    out_P,
    out_mask,
    out_labels,
    out_merges,
):
    """West's reduction of one padded mixture into the ``out_*`` buffers; returns
    ``(cost, overflow, dropped)``."""
    K, d = m_in.shape
    w, m, P, live, labels, n_live = _start(w_in, m_in, P_in, mask)
    S = np.zeros((1, d, d))
    x = np.zeros(d)
    r = np.zeros(d)
    L = np.zeros((d, d))
    Li = np.zeros((d, d))
    ld = np.zeros(K)
    ld2 = np.zeros(K)
    Pinv = np.zeros((K, d, d))
    for k in range(K):
        if live[k]:
            _west_cache(k, P, ld, Pinv, ld2, L, Li)
    for s in range(out_merges.shape[0]):
        out_merges[s, 0] = -1
        out_merges[s, 1] = -1
    total = 0.0
    for step in range(out_merges.shape[0]):
        if n_live <= num_out:
            break
        i = -1
        best = np.inf
        for k in range(K):  # the first smallest weight (or w / det P)
            if live[k]:
                score = w[k] / math.exp(ld[k]) if enhanced else w[k]
                if i < 0 or score < best:
                    best = score
                    i = k
        if metric_ise:  # its first nearest neighbour
            j = -1
            c = np.inf
            for k in range(K):
                if k == i or not live[k]:
                    continue
                for a in range(d):
                    x[a] = m[i, a] - m[k, a]
                    for b in range(d):
                        S[0, a, b] = P[i, a, b] + P[k, a, b]
                ldS, q = _logdet_quad(S, x, L, r)
                jij = math.exp(-0.5 * (d * _LOG_2PI + ldS + q))
                jii = math.exp(-0.5 * (d * _LOG_2PI + ld2[i] + 0.0))
                jkk = math.exp(-0.5 * (d * _LOG_2PI + ld2[k] + 0.0))
                dist = jii + jkk - 2.0 * jij
                if dist < c:
                    c = dist
                    j = k
        else:
            j, c = _kl_argmin(m, P, ld, i, m, Pinv, ld, live, i)
        if j < 0 or not (c <= threshold and math.isfinite(c)):
            break
        _merge_into_slot(i, j, w, m, P, live, labels, S)
        _west_cache(i, P, ld, Pinv, ld2, L, Li)
        n_live -= 1
        out_merges[step, 0] = i
        out_merges[step, 1] = j
        total += c
    overflow, dropped = _finalize(w, m, P, live, labels, out_w, out_m, out_P, out_mask, out_labels)
    return total, overflow, dropped


@njit(**_JIT)
def west(w, m, P, num_out, threshold=np.inf, metric_ise=False, enhanced=False, capacity=-1, mask=None):
    """West's reduction of one padded mixture (West 1993 Sec. 2.3): merge the smallest-weight
    component with its nearest neighbour (``KL(N_i || N_k)``, or the unit-weight ISE with
    ``metric_ise``); ``enhanced`` ranks by ``w / det P``. Arguments and returns as :func:`runnalls`."""
    K, d = m.shape
    cap = K if capacity < 0 else capacity
    live = np.ones(K, np.bool_) if mask is None else mask
    ow, om, oP = np.zeros(cap), np.zeros((cap, d)), np.zeros((cap, d, d))
    omask, olab = np.zeros(cap, np.bool_), np.zeros(K, np.int64)
    merges = np.empty((max(K - num_out, 0), 2), np.int64)
    cost, _, _ = _west_core(
        w, m, P, live, num_out, threshold, metric_ise, enhanced, ow, om, oP, omask, olab, merges
    )
    return ow, om, oP, omask, olab, merges, cost


@njit(parallel=True, **_JIT)
def west_batch(w, m, P, num_out, threshold=np.inf, metric_ise=False, enhanced=False, capacity=-1, mask=None):
    """:func:`west` over a batch ``(B, K, ...)``, mixtures in parallel (``prange``)."""
    B, K, d = m.shape
    cap = K if capacity < 0 else capacity
    live = np.ones((B, K), np.bool_) if mask is None else mask
    ow, om, oP = np.zeros((B, cap)), np.zeros((B, cap, d)), np.zeros((B, cap, d, d))
    omask, olab = np.zeros((B, cap), np.bool_), np.zeros((B, K), np.int64)
    merges = np.empty((B, max(K - num_out, 0), 2), np.int64)
    cost = np.zeros(B)
    for b in prange(B):
        c, _, _ = _west_core(
            w[b],
            m[b],
            P[b],
            live[b],
            num_out,
            threshold,
            metric_ise,
            enhanced,
            ow[b],
            om[b],
            oP[b],
            omask[b],
            olab[b],
            merges[b],
        )
        cost[b] = c
    return ow, om, oP, omask, olab, merges, cost


# ----------------------------------------------------------------------------- GMRC


@register_jitable
def _merge_labels(w, m, P, mask, labels, out_w, out_m, out_P, out_mask):
    """gmjax's ``merge_labels(..., "moment")``: cluster ``c`` (members: live slots with label ``c``)
    into slot ``c``; ``lam = w / W_c`` (``1 / n_c`` for a zero-weight cluster); empty clusters
    ``(0, 0, I)``."""
    K, d = m.shape
    nc = out_w.shape[0]
    count = np.zeros(nc)
    for c in range(nc):
        out_w[c] = 0.0
    for k in range(K):
        c = labels[k]
        if mask[k] and c >= 0 and c < nc:
            out_w[c] += w[k]
            count[c] += 1.0
    lam = np.zeros(K)
    for k in range(K):
        c = labels[k]
        if mask[k] and c >= 0 and c < nc:
            lam[k] = w[k] / out_w[c] if out_w[c] > 0 else 1.0 / count[c]
    for c in range(nc):
        out_mask[c] = count[c] > 0
        for a in range(d):
            out_m[c, a] = 0.0
            for b in range(d):
                out_P[c, a, b] = 0.0
    for k in range(K):
        c = labels[k]
        if mask[k] and c >= 0 and c < nc:
            for a in range(d):
                out_m[c, a] += lam[k] * m[k, a]
    for k in range(K):
        c = labels[k]
        if mask[k] and c >= 0 and c < nc:
            for a in range(d):
                da = m[k, a] - out_m[c, a]
                for b in range(d):
                    out_P[c, a, b] += lam[k] * (P[k, a, b] + da * (m[k, b] - out_m[c, b]))
    for c in range(nc):
        if out_mask[c]:
            for a in range(d):
                for b in range(a + 1, d):
                    v = 0.5 * (out_P[c, a, b] + out_P[c, b, a])
                    out_P[c, a, b] = v
                    out_P[c, b, a] = v
        else:
            out_w[c] = 0.0
            for a in range(d):
                out_m[c, a] = 0.0
                for b in range(d):
                    out_P[c, a, b] = 1.0 if a == b else 0.0


@register_jitable
def _assign_kl(m, P, ld, mask, cm, cinv, cld, cmask, labels):
    """GMRC's assignment: ``labels[k] = argmin_c KL(N_k || N_c)`` over the live centers (first
    minimiser; 0 if every divergence is infinite, as ``jnp.argmin``), ``-1`` for padded slots; the
    arithmetic of :func:`_kl_at` written out in the loop."""
    K, d = m.shape
    for k in range(K):
        if not mask[k]:
            labels[k] = -1
            continue
        best = np.inf
        arg = 0
        for c in range(cm.shape[0]):
            if not cmask[c]:
                continue
            tr = 0.0
            for a in range(d):
                for b in range(d):
                    tr += cinv[c, a, b] * P[k, a, b]
            quad = 0.0
            for a in range(d):
                da = cm[c, a] - m[k, a]
                for b in range(d):
                    quad += da * cinv[c, a, b] * (cm[c, b] - m[k, b])
            kl = 0.5 * (tr + quad - d + cld[c] - ld[k])
            if kl < best:
                best = kl
                arg = c
        labels[k] = arg


@register_jitable
def _gmrc_core(w_in, m_in, P_in, mask, num_out, max_iter, out_w, out_m, out_P, out_mask, out_labels):
    """GMRC of one padded mixture into the ``out_*`` buffers; returns ``(cost, iterations, converged)``."""
    K, d = m_in.shape
    cw, cm, cP = np.zeros(num_out), np.zeros((num_out, d)), np.zeros((num_out, d, d))
    cmask = np.zeros(num_out, np.bool_)
    labels = np.zeros(K, np.int64)
    scratch_merges = np.empty((max(K - num_out, 0), 2), np.int64)
    _runnalls_core(w_in, m_in, P_in, mask, num_out, np.inf, cw, cm, cP, cmask, labels, scratch_merges)
    w = np.zeros(K)
    L = np.zeros((d, d))
    Li = np.zeros((d, d))
    ld = np.zeros(K)
    for k in range(K):
        if mask[k]:
            w[k] = w_in[k]
            ld[k] = _logdet_at(P_in, k, L)
    cinv = np.zeros((num_out, d, d))
    cld = np.zeros(num_out)
    new_labels = np.empty(K, np.int64)
    nw, nm, nP = np.zeros(num_out), np.zeros((num_out, d)), np.zeros((num_out, d, d))
    nmask = np.zeros(num_out, np.bool_)
    it = 0
    done = False
    while (not done) and it < max_iter:
        for c in range(num_out):
            if cmask[c]:
                cld[c] = _logdet_at(cP, c, L)
                _inv_at(cP, c, cinv, c, L, Li)
        _assign_kl(m_in, P_in, ld, mask, cm, cinv, cld, cmask, new_labels)
        _merge_labels(w, m_in, P_in, mask, new_labels, nw, nm, nP, nmask)
        for c in range(num_out):  # an emptied cluster keeps its center, with weight 0
            if nmask[c]:
                cw[c] = nw[c]
                for a in range(d):
                    cm[c, a] = nm[c, a]
                    for b in range(d):
                        cP[c, a, b] = nP[c, a, b]
            else:
                cw[c] = 0.0
        done = True
        for k in range(K):
            if new_labels[k] != labels[k]:
                done = False
            labels[k] = new_labels[k]
        it += 1
    _merge_labels(w, m_in, P_in, mask, labels, nw, nm, nP, nmask)
    for c in range(num_out):
        if nmask[c]:
            cld[c] = _logdet_at(nP, c, L)
            _inv_at(nP, c, cinv, c, L, Li)
    cost = 0.0  # the bound sum_k w_k KL(N_k || N_c(k)) of the final clusters
    for k in range(K):
        c = labels[k]
        if mask[k] and c >= 0:
            cost += w[k] * _kl_at(m_in, P_in, ld, k, nm, cinv, cld, c)
    _finalize(nw, nm, nP, nmask, labels, out_w, out_m, out_P, out_mask, out_labels)
    return cost, it, done


@njit(**_JIT)
def gmrc(w, m, P, num_out, max_iter=50, capacity=-1, mask=None):
    """GMRC of one padded mixture (Schieferdecker & Huber 2009): Runnalls' start, then k-means with
    the KL assignment and moment-preserving merges until the labels stop changing or ``max_iter``.

    Returns:
        ``(w (cap,), m (cap, d), P (cap, d, d), mask (cap,), labels (K,), iterations, converged,
        cost)`` with ``cost = sum_i w_i KL(N_i || N_c(i))``.
    """
    K, d = m.shape
    cap = K if capacity < 0 else capacity
    live = np.ones(K, np.bool_) if mask is None else mask
    ow, om, oP = np.zeros(cap), np.zeros((cap, d)), np.zeros((cap, d, d))
    omask, olab = np.zeros(cap, np.bool_), np.zeros(K, np.int64)
    cost, it, done = _gmrc_core(w, m, P, live, num_out, max_iter, ow, om, oP, omask, olab)
    return ow, om, oP, omask, olab, it, done, cost


@njit(parallel=True, **_JIT)
def gmrc_batch(w, m, P, num_out, max_iter=50, capacity=-1, mask=None):
    """:func:`gmrc` over a batch ``(B, K, ...)``, mixtures in parallel (``prange``)."""
    B, K, d = m.shape
    cap = K if capacity < 0 else capacity
    live = np.ones((B, K), np.bool_) if mask is None else mask
    ow, om, oP = np.zeros((B, cap)), np.zeros((B, cap, d)), np.zeros((B, cap, d, d))
    omask, olab = np.zeros((B, cap), np.bool_), np.zeros((B, K), np.int64)
    iters = np.zeros(B, np.int64)
    conv = np.zeros(B, np.bool_)
    cost = np.zeros(B)
    for b in prange(B):
        c, it, done = _gmrc_core(
            w[b], m[b], P[b], live[b], num_out, max_iter, ow[b], om[b], oP[b], omask[b], olab[b]
        )
        cost[b] = c
        iters[b] = it
        conv[b] = done
    return ow, om, oP, omask, olab, iters, conv, cost
