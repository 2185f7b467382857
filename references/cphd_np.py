"""The GM-CPHD filter per run in plain NumPy / SciPy (the reference for ``gmjax.multitarget.cphd``).

Written straight from B.-T. Vo, B.-N. Vo & A. Cantoni, "Analytic implementations of the
cardinalized probability hypothesis density filter", IEEE TSP 55(7), 2007: the GM-CPHD recursion for
a linear Gaussian model with constant ``P_S``, ``P_D``, no spawning, a Poisson birth RFS (birth
cardinality Poisson with mean ``sum`` of the birth weights) and Poisson clutter
(``p_K = Poisson(lambda_c)``, uniform density ``c``). Python loops over components, measurements and
cardinalities; the elementary symmetric functions by Vieta's recursion in float64, in the linear
domain; the ``Upsilon`` terms as the paper writes them, with ``(1^T w)^{j+u}`` and ``Lambda`` not
normalised (``gmjax`` folds ``1^T w`` into ``Lambda`` and works in the log domain: an independent route).

The reduction is Vo & Ma's Table II as the paper applies it (prune ``w <= T``, merge
``(m_i - m_j)^T P_i^{-1} (m_i - m_j) <= U`` around the heaviest, keep the ``J_max`` heaviest; merged
weights are sums, pruned and capped weight is lost), with gmjax's one convention where the paper is
silent: when every weight is ``<= T`` the heaviest component is kept. The cardinality distribution is
truncated at ``N_max`` after the prediction and renormalised (the cut mass is returned as ``tail``).

:func:`brute_force_update` is a second, independent check of the update for tiny cases: the posterior
cardinality and intensity of an i.i.d. cluster prior by explicit enumeration of the association
hypotheses of the multi-target likelihood.

Nothing here imports gmjax.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.special import comb, gammaln
from scipy.stats import multivariate_normal

from references.reduction_np import merge_moment

__all__ = [
    "esf",
    "poisson_pmf",
    "kf_predict",
    "kf_update",
    "predict_cardinality",
    "upsilon",
    "update",
    "prune_merge",
    "extract",
    "run",
    "brute_force_update",
]


def esf(x):
    """``[e_0, ..., e_M]`` of the values ``x`` (Vieta: the coefficients of ``prod (1 + x_i t)``)."""
    e = np.zeros(len(x) + 1)
    e[0] = 1.0
    for i, xi in enumerate(x):
        for j in range(i + 1, 0, -1):
            e[j] += xi * e[j - 1]
    return e


def poisson_pmf(k, mean):
    """``Poisson(k; mean)`` for an int ``k >= 0``."""
    if mean == 0:
        return 1.0 if k == 0 else 0.0
    return float(np.exp(-mean + k * np.log(mean) - gammaln(k + 1)))


def kf_predict(m, P, F, Q):
    return F @ m, F @ P @ F.T + Q


def kf_update(m, P, z, H, R):
    """``(m+, P+, q(z))``: the Kalman update (Joseph form) and the predicted measurement density."""
    S = H @ P @ H.T + R
    S = 0.5 * (S + S.T)
    K = P @ H.T @ np.linalg.inv(S)
    A = np.eye(len(m)) - K @ H
    return m + K @ (z - H @ m), A @ P @ A.T + K @ R @ K.T, multivariate_normal(H @ m, S).pdf(z)


def predict_cardinality(p, p_s, birth_mean):
    """``p_{k|k-1}(n) = sum_{j<=n} p_Gamma(n - j) sum_{l>=j} C(l, j) P_S^j (1 - P_S)^{l-j} p(l)``,
    ``n = 0 .. N``, renormalised; ``(p_pred, tail)`` with ``tail`` the mass beyond ``N`` cut."""
    N = len(p) - 1
    thinned = np.zeros(N + 1)
    for j in range(N + 1):
        for ell in range(j, N + 1):
            thinned[j] += comb(ell, j) * p_s**j * (1 - p_s) ** (ell - j) * p[ell]
    pred = np.zeros(N + 1)
    for n in range(N + 1):
        for j in range(n + 1):
            pred[n] += poisson_pmf(n - j, birth_mean) * thinned[j]
    total = pred.sum()
    return pred / total, 1.0 - total


def upsilon(u, e, n_z, lam, p_d, W, N):
    """``Upsilon^u[w, Z](n) = sum_{j=0}^{min(|Z|, n)} (|Z| - j)! p_K(|Z| - j) P^n_{j+u}
    (1 - P_D)^{n - (j+u)} e_j(Lambda) / W^{j+u}``, ``n = 0 .. N`` (``P^n_i = 0`` for ``i > n``)."""
    out = np.zeros(N + 1)
    for n in range(N + 1):
        for j in range(min(n_z, n) + 1):
            if j + u > n:
                continue
            clutter = np.exp(gammaln(n_z - j + 1)) * poisson_pmf(n_z - j, lam)
            perm = np.exp(gammaln(n + 1) - gammaln(n - j - u + 1))
            out[n] += clutter * perm * (1 - p_d) ** (n - j - u) * e[j] / W ** (j + u)
    return out


def update(w, m, P, p, Z, H, R, p_d, lam, c):
    """One GM-CPHD update.

    Args:
        w, m, P: the predicted intensity ``(K,)``, ``(K, d)``, ``(K, d, d)``.
        p: ``(N + 1,)`` the predicted cardinality distribution.
        Z: ``(n_z, m)`` the measurement set.

    Returns:
        ``(w, m, P, p, loglik)``: the missed-detection components first, then for each ``z`` in
        order the ``K`` detection components; the updated cardinality distribution and
        ``log p(Z) = log <Upsilon^0, p> + |Z| log c``.
    """
    K, N, n_z = len(w), len(p) - 1, len(Z)
    W = float(np.sum(w))
    upd = [[kf_update(m[i], P[i], z, H, R) for z in Z] for i in range(K)]
    q = np.array([[upd[i][k][2] for k in range(n_z)] for i in range(K)]).reshape(K, n_z)
    # Lambda(w, Z) = {<1, kappa> / kappa(z) P_D w^T q(z)} with <1, kappa> / kappa(z) = 1 / c
    Lam = np.array([p_d * np.dot(w, q[:, k]) / c for k in range(n_z)])
    ups0 = upsilon(0, esf(Lam), n_z, lam, p_d, W, N)
    ups1 = upsilon(1, esf(Lam), n_z, lam, p_d, W, N)
    norm = ups0 @ p
    p_post = ups0 * p / norm
    w_out = [(1 - p_d) * w[i] * (ups1 @ p) / norm for i in range(K)]
    m_out, P_out = list(m), list(P)
    for k in range(n_z):
        ups1_k = upsilon(1, esf(np.delete(Lam, k)), n_z - 1, lam, p_d, W, N)
        for i in range(K):
            w_out.append(p_d * w[i] * q[i, k] / c * (ups1_k @ p) / norm)
            m_out.append(upd[i][k][0])
            P_out.append(upd[i][k][1])
    return np.array(w_out), np.array(m_out), np.array(P_out), p_post, np.log(norm) + n_z * np.log(c)


def prune_merge(w, m, P, T, U, J_max):
    """Vo & Ma Table II: prune ``w <= T``, merge around the heaviest, keep ``J_max``; heaviest first."""
    I = [i for i in range(len(w)) if w[i] > T] or [int(np.argmax(w))]
    out = []
    while I:
        j = max(I, key=lambda i: (w[i], -i))
        L = [i for i in I if (m[i] - m[j]) @ np.linalg.solve(P[i], m[i] - m[j]) <= U]
        out.append(merge_moment(w[L], m[L], P[L]))
        I = [i for i in I if i not in L]
    out = sorted(out, key=lambda c: -c[0])[:J_max]
    return np.array([c[0] for c in out]), np.array([c[1] for c in out]), np.array([c[2] for c in out])


def extract(w, m, p):
    """The MAP cardinality ``n_hat = argmax p`` and the means of the ``n_hat`` heaviest components."""
    n_hat = int(np.argmax(p))
    order = np.argsort(-w, kind="stable")[:n_hat]
    return m[order]


def run(
    scans, F, Q, H, R, birth, *, p_s, p_d, lam, c, n_max, T=1e-5, U=4.0, J_max=100, initial=None, p0=None
):
    """The GM-CPHD filter over a list of measurement sets ``(n_k, m)``.

    Args:
        birth: ``(w_b, m_b, P_b)``, the birth intensity.
        initial: ``(w, m, P)`` at time 0 (default: empty) and ``p0`` its cardinality distribution
            (default: a point mass at 0).

    Returns:
        One dict per step: ``w``, ``m``, ``P`` (reduced, heaviest first), ``p`` (posterior cardinality),
        ``tail`` (mass cut by the prediction), ``estimates``, ``loglik``, ``w_updated`` (before reduction).
    """
    d = F.shape[0]
    w, m, P = initial if initial is not None else (np.zeros(0), np.zeros((0, d)), np.zeros((0, d, d)))
    p = np.eye(n_max + 1)[0] if p0 is None else np.asarray(p0, float)
    wb, mb, Pb = (np.asarray(a, float) for a in birth)
    out = []
    for Z in scans:
        pred = [kf_predict(m[i], P[i], F, Q) for i in range(len(w))]
        w_p = np.concatenate([p_s * np.asarray(w), wb])
        m_p = np.array([a for a, _ in pred] + list(mb)).reshape(-1, d)
        P_p = np.array([b for _, b in pred] + list(Pb)).reshape(-1, d, d)
        p, tail = predict_cardinality(p, p_s, float(wb.sum()))
        w_u, m_u, P_u, p, loglik = update(
            w_p, m_p, P_p, p, np.asarray(Z, float).reshape(-1, H.shape[0]), H, R, p_d, lam, c
        )
        w, m, P = prune_merge(w_u, m_u, P_u, T, U, J_max)
        out.append(
            dict(w=w, m=m, P=P, p=p, tail=tail, estimates=extract(w, m, p), loglik=loglik, w_updated=w_u)
        )
    return out


def brute_force_update(w, m, P, p, Z, H, R, p_d, lam, c):
    """The exact Bayes update of an i.i.d. cluster prior, by enumerating association hypotheses.

    The prior: ``n ~ p``, targets i.i.d. with density ``s = sum_i (w_i / W) N(m_i, P_i)``. The
    multi-target likelihood (Mahler) of the set ``Z`` given ``x_1 .. x_n`` is a sum over the
    hypotheses ``theta``, which map each target to "missed" or to a measurement, injectively:
    ``prod_{detected} P_D g(z_theta(i) | x_i) prod_{missed} (1 - P_D) * |C|! p_K(|C|) prod_{z in C} c``
    with ``C`` the unassigned (clutter) measurements. Integrating the targets against ``s`` replaces
    ``g(z | x_i)`` by ``L(z) = sum_i s_i q_i(z)``. Every ``(n, theta)`` is enumerated (``(|Z| + 1)^n``
    maps per ``n``; keep ``N`` and ``|Z|`` tiny).

    Returns:
        ``(p_post (N + 1,), missed (K,), detected (K, |Z|), loglik)``: the posterior cardinality, the
        weights of the posterior intensity's components (``missed[i]`` on ``N(m_i, P_i)`` and
        ``detected[i, k]`` on component ``i`` updated with ``z_k``: the exact posterior PHD) and
        ``log p(Z)``, the log of the set density of ``Z``.
    """
    w = np.asarray(w, float)
    K, N, n_z = len(w), len(p) - 1, len(Z)
    s = w / w.sum()
    q = np.array([[multivariate_normal(H @ m[i], H @ P[i] @ H.T + R).pdf(z) for z in Z] for i in range(K)])
    q = q.reshape(K, n_z)
    L = s @ q  # (n_z,)
    joint = np.zeros(N + 1)
    missed_acc = 0.0  # E[#missed targets] (unnormalised)
    det_acc = np.zeros(n_z)  # P(z is a target's) (unnormalised)
    for n in range(N + 1):
        for theta in itertools.product(range(-1, n_z), repeat=n):
            used = [a for a in theta if a >= 0]
            if len(used) != len(set(used)):
                continue
            n_c = n_z - len(used)
            term = p[n] * np.exp(gammaln(n_c + 1)) * poisson_pmf(n_c, lam) * c**n_c
            for a in theta:
                term *= (1 - p_d) if a < 0 else p_d * L[a]
            joint[n] += term
            missed_acc += term * (n - len(used))
            for a in used:
                det_acc[a] += term
    total = joint.sum()
    missed = missed_acc / total * s
    detected = (det_acc / total)[None, :] * s[:, None] * q / np.where(L > 0, L, 1.0)[None, :]
    return joint / total, missed, detected, float(np.log(total))
