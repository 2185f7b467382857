"""Plain NumPy per-mixture reductions, written straight from the papers (the baseline a user would
otherwise write, and the independent check of ``gmjax.reduction``).

A mixture is ``(w (n,), m (n, d), P (n, d, d))`` of live components only. Every function works on
Python lists of components and ``np.linalg``; no vectorisation tricks. The merge conventions
(which slot keeps the merged component, tie-breaking by the first minimiser in slot order) are
the ones documented in ``gmjax/reduction/_greedy.py`` so that merge sequences can be compared.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "merge_moment",
    "merge_pair",
    "runnalls",
    "salmond",
    "west",
    "kmeans",
    "prune_threshold",
    "prune_top",
    "prune_censored",
    "ise",
    "brute_force",
    "vo_ma",
]


def merge_moment(w, m, P):
    """Seed 002 eqs 70–72 (seed 003 eq 18 form): weight, mean and covariance of the merged set."""
    w = np.asarray(w, float)
    W = w.sum()
    mu = (w[:, None] * m).sum(0) / W
    C = np.zeros((m.shape[1], m.shape[1]))
    for k in range(len(w)):
        dev = m[k] - mu
        C += w[k] * (P[k] + np.outer(dev, dev))
    return W, mu, C / W


def merge_pair(w1, m1, P1, w2, m2, P2):
    W = w1 + w2
    l1, l2 = w1 / W, w2 / W
    diff = m1 - m2
    mu = l1 * m1 + l2 * m2
    C = l1 * P1 + l2 * P2 + l1 * l2 * np.outer(diff, diff)
    return W, mu, 0.5 * (C + C.T)


def _logdet(P):
    sign, val = np.linalg.slogdet(P)
    return val


def _gauss(x, m, P):
    d = len(m)
    diff = x - m
    return np.exp(-0.5 * (d * np.log(2 * np.pi) + _logdet(P) + diff @ np.linalg.solve(P, diff)))


def _greedy_pairs(w, m, P, num_out, threshold, cost):
    """Merge the upper-triangle argmin pair (first in row-major slot order) into its lower slot."""
    slots = [(float(w[k]), np.array(m[k], float), np.array(P[k], float)) for k in range(len(w))]
    alive = list(range(len(w)))
    labels = list(range(len(w)))
    merges, total = [], 0.0
    while len(alive) > num_out:
        best, bi, bj = np.inf, -1, -1
        for a in range(len(alive)):
            for b in range(a + 1, len(alive)):
                i, j = alive[a], alive[b]
                c = cost(slots[i], slots[j])
                if c < best:
                    best, bi, bj = c, i, j
        if not (best <= threshold) or not np.isfinite(best):
            break
        slots[bi] = merge_pair(*slots[bi], *slots[bj])
        alive.remove(bj)
        labels = [bi if lab == bj else lab for lab in labels]
        merges.append((bi, bj))
        total += best
    return _pack(slots, alive, labels, merges, total)


def _pack(slots, alive, labels, merges, total):
    pos = {s: k for k, s in enumerate(alive)}
    w = np.array([slots[s][0] for s in alive])
    m = np.array([slots[s][1] for s in alive])
    P = np.array([slots[s][2] for s in alive])
    return {
        "w": w,
        "m": m,
        "P": P,
        "labels": np.array([pos[lab] for lab in labels]),
        "merges": merges,
        "cost": total,
    }


def runnalls(w, m, P, num_out, threshold=np.inf):
    """Runnalls (2007): greedy merging by the KL upper bound
    ``B = 1/2 [(w_i + w_j) log|P_ij| - w_i log|P_i| - w_j log|P_j|]``."""

    def cost(a, b):
        W, _, Pij = merge_pair(*a, *b)
        return 0.5 * (W * _logdet(Pij) - a[0] * _logdet(a[2]) - b[0] * _logdet(b[2]))

    return _greedy_pairs(w, m, P, num_out, threshold, cost)


def salmond(w, m, P, num_out, threshold=np.inf):
    """Salmond (1990) joining: ``D^2 = w_i w_j / (w_i + w_j) (m_i - m_j)^T Ptot^{-1} (m_i - m_j)``."""
    wn = np.asarray(w) / np.sum(w)
    _, _, Ptot = merge_moment(wn, np.asarray(m), np.asarray(P))
    Pinv = np.linalg.inv(Ptot)

    def cost(a, b):
        diff = a[1] - b[1]
        return a[0] * b[0] / (a[0] + b[0]) * diff @ Pinv @ diff

    return _greedy_pairs(w, m, P, num_out, threshold, cost)


def _kl(m1, P1, m2, P2):
    d = len(m1)
    P2i = np.linalg.inv(P2)
    diff = m2 - m1
    return 0.5 * (np.trace(P2i @ P1) + diff @ P2i @ diff - d + _logdet(P2) - _logdet(P1))


def west(w, m, P, num_out, threshold=np.inf, metric="kl", enhanced=False):
    """West (1993): merge the smallest-weight component with its nearest neighbour (KL or ISE)."""
    slots = [(float(w[k]), np.array(m[k], float), np.array(P[k], float)) for k in range(len(w))]
    alive = list(range(len(w)))
    labels = list(range(len(w)))
    merges, total = [], 0.0
    while len(alive) > num_out:
        if enhanced:
            scores = [slots[s][0] / np.linalg.det(slots[s][2]) for s in alive]
        else:
            scores = [slots[s][0] for s in alive]
        i = alive[int(np.argmin(scores))]
        best, j = np.inf, -1
        for k in alive:
            if k == i:
                continue
            if metric == "kl":
                dist = _kl(slots[i][1], slots[i][2], slots[k][1], slots[k][2])
            else:
                dist = (
                    _gauss(slots[i][1], slots[i][1], 2 * slots[i][2])
                    + _gauss(slots[k][1], slots[k][1], 2 * slots[k][2])
                    - 2 * _gauss(slots[i][1], slots[k][1], slots[i][2] + slots[k][2])
                )
            if dist < best:
                best, j = dist, k
        if not (best <= threshold) or not np.isfinite(best):
            break
        slots[i] = merge_pair(*slots[i], *slots[j])
        alive.remove(j)
        labels = [i if lab == j else lab for lab in labels]
        merges.append((i, j))
        total += best
    return _pack(slots, alive, labels, merges, total)


def _wmaha(a, b):
    """Seed 002 eq 69."""
    diff = a[1] - b[1]
    return a[0] * b[0] / (a[0] + b[0]) * diff @ np.linalg.solve(a[2] + b[2], diff)


def kmeans(w, m, P, num_out, max_iter=100, tol=0.0):
    """Seed 002 Algorithm 3: farthest-point initialisation, eq-69 assignment, eqs 70–72 merge."""
    n = len(w)
    comps = [(float(w[k]), np.array(m[k], float), np.array(P[k], float)) for k in range(n)]
    if n <= num_out:
        return {
            "w": np.array(w, float),
            "m": np.array(m, float),
            "P": np.array(P, float),
            "labels": np.arange(n),
            "iterations": 0,
        }
    first = int(np.argmax(w))
    centers = [comps[first]]
    for _ in range(1, num_out):
        min_dist = [min(_wmaha(comps[j], c) for c in centers) for j in range(n)]
        k = int(np.argmax(min_dist))
        centers.append(comps[k])
    labels = None
    it = 0
    while it < max_iter:
        labels = [int(np.argmin([_wmaha(comps[i], c) for c in centers])) for i in range(n)]
        new = []
        for c in range(num_out):
            members = [i for i in range(n) if labels[i] == c]
            if members:
                new.append(
                    merge_moment(
                        np.array([w[i] for i in members]), np.array(m)[members], np.array(P)[members]
                    )
                )
            else:
                new.append(centers[c])
        it += 1
        change = max(
            max(abs(a[0] - b[0]), np.abs(a[1] - b[1]).max(), np.abs(a[2] - b[2]).max())
            for a, b in zip(new, centers)
        )
        centers = new
        if change <= tol:
            break
    used = sorted(set(labels))
    pos = {c: k for k, c in enumerate(used)}
    return {
        "w": np.array([centers[c][0] for c in used]),
        "m": np.array([centers[c][1] for c in used]),
        "P": np.array([centers[c][2] for c in used]),
        "labels": np.array([pos[lab] for lab in labels]),
        "iterations": it,
    }


def prune_threshold(w, threshold):
    """Indices kept (heaviest first) and renormalised weights."""
    w = np.asarray(w, float)
    keep = [k for k in range(len(w)) if w[k] >= threshold]
    if not keep:
        keep = [int(np.argmax(w))]
    keep = sorted(keep, key=lambda k: (-w[k], k))
    return keep, w[keep] * w.sum() / w[keep].sum()


def prune_top(w, num_out):
    w = np.asarray(w, float)
    keep = sorted(range(len(w)), key=lambda k: (-w[k], k))[:num_out]
    return keep, w[keep] * w.sum() / w[keep].sum()


def prune_censored(w, rho=0.9544, n_u=None):
    """Seed 000 eqs 19–22 with the ascending order statistic loop written out."""
    w = np.asarray(w, float)
    I = len(w)
    asc = sorted(range(I), key=lambda k: (w[k], -k))  # ascending; ties: higher index first
    ws = w[asc]
    total = ws.sum()
    n_max = 1
    for n in range(1, I + 1):  # 1-based n
        gamma = ws[n - 1 :].sum() / total
        if gamma >= rho:
            n_max = n
    N = I - n_max + 1
    if n_u is not None:
        N = min(N, n_u)
    keep = list(reversed(asc))[:N]
    return keep, w[keep] / (1.0 - w[asc[: I - N]].sum() / total)


def ise(w1, m1, P1, w2, m2, P2):
    """Closed-form ISE between two mixtures (seed 000 eqs 31, 35)."""

    def inner(wa, ma, Pa, wb, mb, Pb):
        return sum(
            wa[i] * wb[j] * _gauss(ma[i], mb[j], Pa[i] + Pb[j])
            for i in range(len(wa))
            for j in range(len(wb))
        )

    return inner(w1, m1, P1, w1, m1, P1) - 2 * inner(w1, m1, P1, w2, m2, P2) + inner(w2, m2, P2, w2, m2, P2)


def _partitions(n, k):
    """Set partitions of ``range(n)`` into at most ``k`` blocks (restricted growth strings)."""

    def rec(prefix, maxb):
        if len(prefix) == n:
            yield list(prefix)
            return
        for b in range(min(maxb + 2, k)):
            yield from rec(prefix + [b], max(maxb, b))

    yield from rec([], -1)


def brute_force(w, m, P, num_out):
    """The ISE-optimal moment-preserving merge over every partition into at most ``num_out``
    clusters (exhaustive)."""
    w, m, P = np.asarray(w, float), np.asarray(m, float), np.asarray(P, float)
    best = (np.inf, None)
    for lab in _partitions(len(w), num_out):
        lab = np.array(lab)
        comps = [merge_moment(w[lab == c], m[lab == c], P[lab == c]) for c in range(lab.max() + 1)]
        wr = np.array([c[0] for c in comps])
        mr = np.array([c[1] for c in comps])
        Pr = np.array([c[2] for c in comps])
        val = ise(w, m, P, wr, mr, Pr)
        if val < best[0]:
            best = (val, (wr, mr, Pr, lab))
    return best


def vo_ma(w, m, P, prune, merge, max_components):
    """Vo & Ma (2006) GM-PHD pruning and merging (Table II), renormalised to the input's total."""
    w, m, P = np.asarray(w, float), np.asarray(m, float), np.asarray(P, float)
    total = w.sum()
    I = [k for k in range(len(w)) if w[k] > prune]
    if not I:
        I = [int(np.argmax(w))]
    out = []
    while I:
        j = max(I, key=lambda k: (w[k], -k))
        L = [i for i in I if (m[i] - m[j]) @ np.linalg.solve(P[i], m[i] - m[j]) <= merge]
        out.append(merge_moment(w[L], m[L], P[L]))
        I = [i for i in I if i not in L]
    out = sorted(out, key=lambda c: -c[0])[:max_components]
    W = np.array([c[0] for c in out])
    scale = total / W.sum()
    return W * scale, np.array([c[1] for c in out]), np.array([c[2] for c in out])


def _mix(slots, idx, scale=1.0):
    return (
        np.array([slots[s][0] * scale for s in idx]),
        np.array([slots[s][1] for s in idx]),
        np.array([slots[s][2] for s in idx]),
    )


def williams(w, m, P, num_out, threshold=np.inf, allow_prune=True):
    """Williams & Maybeck (2003): every step scores every pair merge and every single deletion
    (with renormalisation) by the ISE of the result to the original, directly with :func:`ise`."""
    w0, m0, P0 = np.asarray(w, float), np.asarray(m, float), np.asarray(P, float)
    slots = [(float(w0[k]), m0[k].copy(), P0[k].copy()) for k in range(len(w0))]
    alive = list(range(len(w0)))
    actions = []
    cost = 0.0
    while len(alive) > num_out:
        best = (np.inf, None)
        for a in range(len(alive)):
            for b in range(a + 1, len(alive)):
                i, j = alive[a], alive[b]
                trial = list(slots)
                trial[i] = merge_pair(*slots[i], *slots[j])
                idx = [k for k in alive if k != j]
                val = ise(w0, m0, P0, *_mix(trial, idx))
                if val < best[0]:
                    best = (val, ("merge", i, j))
        if allow_prune and len(alive) > 1:
            Wt = sum(slots[k][0] for k in alive)
            for i in alive:
                rem = Wt - slots[i][0]
                if rem <= 0:
                    continue
                idx = [k for k in alive if k != i]
                val = ise(w0, m0, P0, *_mix(slots, idx, Wt / rem))
                if val < best[0]:
                    best = (val, ("prune", i, -1))
        val, act = best
        val = max(val, 0.0)
        if act is None or not val <= threshold:
            break
        kind, i, j = act
        if kind == "merge":
            slots[i] = merge_pair(*slots[i], *slots[j])
            alive.remove(j)
            actions.append((i, j))
        else:
            Wt = sum(slots[k][0] for k in alive)
            s = Wt / (Wt - slots[i][0])
            alive.remove(i)
            for k in alive:
                slots[k] = (slots[k][0] * s, slots[k][1], slots[k][2])
            actions.append((i, -1))
        cost = val
    wr, mr, Pr = _mix(slots, alive)
    return {"w": wr, "m": mr, "P": Pr, "actions": actions, "cost": cost}


def gmrc(w, m, P, num_out, max_iter=50):
    """Schieferdecker & Huber (2009): Runnalls initialisation, then k-means with the assignment
    ``argmin_c KL(N_i || N_c)`` and moment-preserving cluster merges until labels stop changing."""
    w, m, P = np.asarray(w, float), np.asarray(m, float), np.asarray(P, float)
    r = runnalls(w, m, P, num_out)
    labels = r["labels"].copy()
    centers = [(r["w"][c], r["m"][c], r["P"][c]) for c in range(len(r["w"]))]
    it = 0
    while it < max_iter:
        new_labels = np.array(
            [int(np.argmin([_kl(m[i], P[i], c[1], c[2]) for c in centers])) for i in range(len(w))]
        )
        new_centers = []
        for c in range(len(centers)):
            sel = new_labels == c
            if sel.any():
                new_centers.append(merge_moment(w[sel], m[sel], P[sel]))
            else:
                new_centers.append((0.0, centers[c][1], centers[c][2]))
        it += 1
        done = np.array_equal(new_labels, labels)
        labels, centers = new_labels, new_centers
        if done:
            break
    used = sorted(set(labels.tolist()))
    return {
        "w": np.array([centers[c][0] for c in used]),
        "m": np.array([centers[c][1] for c in used]),
        "P": np.array([centers[c][2] for c in used]),
        "labels": np.array([used.index(lab) for lab in labels]),
        "iterations": it,
    }


def cowa_weights(S, b, total):
    """Active-set solution of ``min w^T S w - 2 b^T w`` s.t. ``sum w = total``, ``w >= 0``
    (all negative components dropped at once per round)."""
    n = len(b)
    act = np.ones(n, bool)
    w = np.zeros(n)
    for _ in range(n + 1):
        idx = np.flatnonzero(act)
        Sa = S[np.ix_(idx, idx)]
        u = np.linalg.solve(Sa, b[idx])
        v = np.linalg.solve(Sa, np.ones(len(idx)))
        nu = (total - u.sum()) / v.sum()
        w = np.zeros(n)
        w[idx] = u + nu * v
        neg = act & (w < 0)
        if not neg.any():
            break
        act &= ~neg
    return w, act


def runnalls_cached(w, m, P, num_out):
    """Runnalls with the cost matrix computed once (vectorised NumPy) and one row/column updated
    per merge — the efficient per-mixture implementation (as in the Tracker Component Library),
    the fairer speed baseline. Same conventions and merge sequence as :func:`runnalls`."""
    w = np.array(w, float)
    m = np.array(m, float)
    P = np.array(P, float)
    n = len(w)
    alive = np.ones(n, bool)
    logdets = np.linalg.slogdet(P)[1]

    def row(i):
        W = w[i] + w
        l1 = w[i] / W
        l2 = w / W
        diff = m[i] - m
        Pij = (
            l1[:, None, None] * P[i]
            + l2[:, None, None] * P
            + (l1 * l2)[:, None, None] * (diff[:, :, None] * diff[:, None, :])
        )
        return 0.5 * (W * np.linalg.slogdet(Pij)[1] - w[i] * logdets[i] - w * logdets)

    C = np.stack([row(i) for i in range(n)])
    iu = np.triu(np.ones((n, n), bool), 1)
    merges = []
    count = n
    while count > num_out:
        Cm = np.where(iu & alive[:, None] & alive[None, :], C, np.inf)
        flat = int(np.argmin(Cm))
        i, j = divmod(flat, n)
        W, mu, Pm = merge_pair(w[i], m[i], P[i], w[j], m[j], P[j])
        w[i], m[i], P[i] = W, mu, Pm
        logdets[i] = np.linalg.slogdet(Pm)[1]
        alive[j] = False
        w[j] = 0.0
        count -= 1
        r = row(i)
        C[i, :] = r
        C[:, i] = r
        merges.append((i, j))
    idx = np.flatnonzero(alive)
    return {"w": w[idx], "m": m[idx], "P": P[idx], "merges": merges}
