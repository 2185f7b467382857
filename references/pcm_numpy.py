"""Plain NumPy/Python reference for prune-cluster-merge (seed 000) and cluster-merge (seed 003).

Written straight from the papers with Python sets and loops, one mixture at a time: the baseline a
user would otherwise write, and the independent check of ``gmjax.reduction.clustering``,
``gmjax.reduction.eise``, ``gmjax.reduction.pcm`` and ``gmjax.reduction.gmrcm``. The readings of the
ambiguous steps are the ones documented in ``gmjax/reduction/clustering.py`` (Mahalanobis confidence
ellipsoid, lexicographic pair order, subset kept whole, ties of eq 28 to the lower-indexed cluster).
"""

from __future__ import annotations

import math

import numpy as np

#: The 1-D static mixtures of seed 000 §IV-A (Figs 4-6): name -> (weights, means, standard
#: deviations). The tests (``tests/eise_cases.py``, which run seed 003's reducer on them too) and
#: ``benchmarks/bench_pcm_static.py`` read them from here.
STATIC_CASES = {
    "unimodal": ([0.3, 0.1, 0.4, 0.2], [1, 1.5, 2, 3], [1, 1.2, 0.5, 0.8]),
    "bimodal": ([0.3, 0.1, 0.4, 0.2], [0.5, 2, 3.5, 4], [1, 1.2, 0.5, 0.8]),
    "multimodal": (
        [0.1, 0.05, 0.35, 0.1, 0.1, 0.2, 0.04, 0.06],
        [0.5, 2, 3.5, 4, 5, -1, 0, 1],
        [1, 1.2, 0.5, 0.8, 0.2, 0.3, 4, 3],
    ),
}


def _n_pdf(x, m, P):
    d = len(m)
    diff = np.asarray(x, float) - np.asarray(m, float)
    sol = np.linalg.solve(P, diff)
    return math.exp(-0.5 * diff @ sol) / math.sqrt((2 * math.pi) ** d * np.linalg.det(P))


def prune_censored(w, m, P, rho=0.9544, max_components=None):
    """Seed 000 eqs 19–22 and 41: indices kept (heaviest first) and reset weights."""
    w = np.asarray(w, float)
    n = len(w)
    order = np.argsort(w, kind="stable")  # ascending, eq 19
    ws = w[order]
    total = ws.sum()
    n_max = 1
    for k in range(1, n + 1):  # gamma_k = sum_{l >= k} w_(l) / sum w  (eq 20)
        if ws[k - 1 :].sum() / total >= rho:
            n_max = k  # the largest n with gamma_n >= rho (eq 21)
    keep_n = n - n_max + 1
    if max_components is not None:
        keep_n = min(keep_n, max_components)  # eq 22
    kept = order[::-1][:keep_n]
    wk = w[kept] / w[kept].sum()  # eq 41
    return kept, wk, m[kept], P[kept]


def judgment(m, P, lam, triangular=False, range_scale=0.5):
    n = len(m)
    r = np.zeros((n, n), bool)
    for i in range(n):
        for j in range(n):
            if triangular and j < i:
                continue
            diff = m[j] - m[i]
            di = math.sqrt(max(diff @ np.linalg.solve(P[i], diff), 0.0))
            dj = math.sqrt(max(diff @ np.linalg.solve(P[j], diff), 0.0))
            r[i, j] = max(di, dj) <= range_scale * lam  # scope s*lam*sigma (eq 24)
    return r


def cluster(m, P, lam, triangular=False, subset_rule="split", range_scale=0.5):
    """Seed 000 eqs 23–28 with sets; returns a list (indexed by head) of sets or None."""
    n = len(m)
    r = judgment(m, P, lam, triangular, range_scale)
    clusters = [set(np.flatnonzero(r[i]).tolist()) for i in range(n)]  # eq 25
    for i in range(n):  # Step 1: combine identical clusters
        for j in range(i):
            if clusters[j] and clusters[i] == clusters[j]:
                clusters[i] = set()
                break
    for i in range(n):  # Step 3: all pairs, in order
        for j in range(i + 1, n):
            ci, cj = clusters[i], clusters[j]
            ov = ci & cj
            if not ov:  # Situation 1
                continue
            if ci == cj:
                clusters[j] = set()
            elif cj <= ci:  # Situation 3
                if subset_rule == "split":  # seed 000: keep the subset and the complement
                    clusters[i] = ci - cj
                else:  # seed 003 H2: the superset keeps everything
                    clusters[j] = set()
            elif ci <= cj:
                if subset_rule == "split":
                    clusters[j] = cj - ci
                else:
                    clusters[i] = set()
            else:  # Situation 2
                ri, rj = ci - ov, cj - ov  # eq 27: the renewed clusters
                new_i, new_j = set(ri), set(rj)
                for c in sorted(ov):  # eq 28 against the renewed clusters, Step 2.3
                    d_i = min(np.linalg.norm(m[t] - m[c]) for t in ri)
                    d_j = min(np.linalg.norm(m[t] - m[c]) for t in rj)
                    if d_i <= d_j:
                        new_i.add(c)
                    else:
                        new_j.add(c)
                clusters[i], clusters[j] = new_i, new_j
    return clusters


def merge_ci(w, m, P):
    """Seed 000 eqs 38–39 with normalised weights; merged weight = sum (eq 41 text)."""
    W = w.sum()
    om = w / W
    info = sum(o * np.linalg.inv(Pk) for o, Pk in zip(om, P))
    Pbar = np.linalg.inv(info)
    mbar = Pbar @ sum(o * np.linalg.solve(Pk, mk) for o, mk, Pk in zip(om, m, P))
    return W, mbar, 0.5 * (Pbar + Pbar.T)


def merge_moment(w, m, P):
    """Seed 003 eqs 16–18."""
    W = w.sum()
    mbar = sum(wk * mk for wk, mk in zip(w, m)) / W
    Pbar = sum(wk * (Pk + np.outer(mk - mbar, mk - mbar)) for wk, mk, Pk in zip(w, m, P)) / W
    return W, mbar, 0.5 * (Pbar + Pbar.T)


def cluster_ise(w, m, P, W, mbar, Pbar):
    """``∫ (f_c - q_c)^2`` by seed 000 eq 35 with explicit double loops."""
    jhh = sum(w[a] * w[b] * _n_pdf(m[a], m[b], P[a] + P[b]) for a in range(len(w)) for b in range(len(w)))
    jhr = sum(w[a] * W * _n_pdf(m[a], mbar, P[a] + Pbar) for a in range(len(w)))
    jrr = W * W * _n_pdf(mbar, mbar, 2 * Pbar)
    return jhh - 2 * jhr + jrr


def reduce_fixed(
    w,
    m,
    P,
    lam,
    *,
    merge="ci",
    triangular=False,
    subset_rule="split",
    alpha=0.001,
    reg="exp",
    ise_scale=0.5,
    range_scale=0.5,
):
    """Cluster at ``λ``, merge each cluster, and the EISE (seed 000 eq 29 / seed 003 eq 10)."""
    clusters = [sorted(c) for c in cluster(m, P, lam, triangular, subset_rule, range_scale) if c]
    fn = merge_ci if merge == "ci" else merge_moment
    out_w, out_m, out_P, total = [], [], [], 0.0
    for c in clusters:
        idx = np.asarray(c)
        W, mb, Pb = fn(w[idx], m[idx], P[idx])
        out_w.append(W)
        out_m.append(mb)
        out_P.append(Pb)
        total += cluster_ise(w[idx], m[idx], P[idx], W, mb, Pb)
    n_out = len(clusters)
    n_ref = len(w)
    penalty = alpha * (math.exp(n_out / n_ref) if reg == "exp" else math.log10(n_out))
    return (np.asarray(out_w), np.asarray(out_m), np.asarray(out_P), clusters, ise_scale * total + penalty)


def pcm_grid(
    w,
    m,
    P,
    *,
    rho=0.9544,
    max_components=None,
    lam_lo=1.0,
    lam_hi=3.0,
    grid=11,
    alpha=0.001,
    prune=True,
    range_scale=0.5,
):
    """Seed 000 Table 1 with a grid search over λ in place of Newton steps (the NumPy baseline)."""
    if prune:
        _, w, m, P = prune_censored(w, m, P, rho, max_components)
    best = None
    for lam in np.linspace(lam_lo, lam_hi, grid):
        res = reduce_fixed(w, m, P, lam, merge="ci", alpha=alpha, range_scale=range_scale)
        if best is None or res[-1] < best[1][-1]:
            best = (lam, res)
    return best


def ise_mixtures(wa, ma, Pa, wb, mb, Pb):
    """ISE between two mixtures (seed 000 eq 42) by double loops."""

    def inner(w1, m1, P1, w2, m2, P2):
        return sum(
            w1[a] * w2[b] * _n_pdf(m1[a], m2[b], P1[a] + P2[b])
            for a in range(len(w1))
            for b in range(len(w2))
        )

    return inner(wa, ma, Pa, wa, ma, Pa) - 2 * inner(wa, ma, Pa, wb, mb, Pb) + inner(wb, mb, Pb, wb, mb, Pb)
