"""The GM-LMB filter per run in plain NumPy / SciPy (the reference for ``gmjax.multitarget.lmb``).

Written from S. Reuter, B.-T. Vo, B.-N. Vo & K. Dietmayer, "The labeled multi-Bernoulli filter", IEEE
TSP 62(12), 2014: the LMB prediction (Prop. 2, Sec. III-A), the update through the delta-GLMB and its
LMB approximation (Sec. III-B/C) and the state extraction (Sec. IV), for a linear Gaussian model with
constant ``P_S``, ``P_D`` and Poisson clutter of rate ``lambda_c`` and uniform density ``c``
(``kappa(z) = lambda_c c``). The ranked-assignment truncation of the association hypotheses is replaced,
as in Vo's public MATLAB LMB code, by the Gibbs sampler of B.-N. Vo, B.-T. Vo & H. G. Hoang, "An
efficient implementation of the generalized labeled multi-Bernoulli filter", IEEE TSP 65(8), 2017
(Algorithm 1, with the joint existence / association variable): the distinct sampled hypotheses are
kept, weighted exactly and renormalised.

Every array is padded to a fixed size (:class:`Tracks`), with the same order of operations, tie rules
and use of the uniform draws as gmjax, so the two can be compared step by step: the Gibbs sweep draws
``u[g - 1, i]`` for track ``i`` of row ``g``. Python loops over tracks, components, measurements and
Gibbs rows; float64 throughout, ``log 0 = -inf``.

:func:`exact_marginals` is the independent check of the Gibbs truncation for tiny cases: the exact
marginals by enumerating every joint assignment (each track not existing, missed, or detected by a
measurement that no other track takes).

Conventions where the spec is silent (resolved here; gmjax is to agree):

* a measurement row with any NaN is absent;
* a detection block whose ``sum_c w_ic q_icj`` is 0 (then ``beta_i(1+j) = 0``) has weights 0, not
  ``0 / 0``; its components stay live (only absent ``z_j`` and empty slots are masked), so they are
  dropped by any ``component_threshold > 0`` and kept (with weight 0, last) by ``0``;
* a track with ``r' > 0`` none of whose components reaches ``component_threshold`` keeps its heaviest
  component (ties: the lower flat slot) alone, with weight 1; the kept weights are renormalised by
  their sum taken in decreasing-weight order;
* only live tracks (``r' > 0`` after the reduction) compete for the track capacity, so an empty slot
  never triggers ``overflow``, whatever ``existence_threshold``;
* when every kept hypothesis has zero weight (a single Gibbs row whose start is infeasible, or no
  feasible joint assignment at all, e.g. two tracks with ``r = P_D = 1`` and one measurement), the
  weights, ``r'`` and ``beta`` are zero, every track becomes empty and ``loglik = -inf``.

Nothing here imports gmjax.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np

__all__ = [
    "Tracks",
    "UpdateResult",
    "Estimates",
    "Exact",
    "empty_tracks",
    "gaussian_logpdf",
    "kf_update",
    "predict",
    "kf_terms",
    "log_eta_from_q",
    "log_eta",
    "gibbs",
    "unique_rows",
    "hypothesis_weights",
    "update",
    "cardinality_pmf",
    "extract",
    "exact_marginals",
    "run",
]

NEG_INF = -np.inf


class Tracks(NamedTuple):
    """A padded labeled multi-Bernoulli set: ``N`` track slots of ``J`` components in ``d`` dims."""

    r: np.ndarray  # (N,) existence probabilities, 0 for an empty slot
    labels: np.ndarray  # (N, 2) int (birth step k, birth slot b); (-1, -1) for an empty slot
    mask: np.ndarray  # (N,) bool, live track slots
    w: np.ndarray  # (N, J) component weights, summing to 1 over the live components of a live track
    m: np.ndarray  # (N, J, d) means (0 in an empty slot)
    P: np.ndarray  # (N, J, d, d) covariances (identity in an empty slot)
    cmask: np.ndarray  # (N, J) bool, live components


class UpdateResult(NamedTuple):
    tracks: Tracks  # the posterior, n_tracks slots of n_components components
    samples: np.ndarray  # (G, N) int, the Gibbs rows (choice index a in 0 .. M+1 per track)
    kept: np.ndarray  # (G,) bool, the first occurrence of each distinct row
    weights: np.ndarray  # (G,) normalised hypothesis weights (0 for rows not kept)
    r: np.ndarray  # (N,) the marginal existence probabilities r' of the predicted tracks
    beta: np.ndarray  # (N, M+1) beta[i, a-1] = P(track i chose a), a = 1 (missed), 1+j (z_j)
    loglik: float  # the log-likelihood of Z (a lower bound under the truncation)
    overflow: bool  # a track with r' >= existence_threshold was dropped by the capacity
    log_eta: np.ndarray  # (N, M+2) the joint costs of step 2


class Estimates(NamedTuple):
    states: np.ndarray  # (E, d)
    labels: np.ndarray  # (E, 2) int, (-1, -1) where mask is False
    mask: np.ndarray  # (E,) bool
    n_hat: int  # the MAP cardinality (may exceed E)


class Exact(NamedTuple):
    r: np.ndarray  # (N,) exact r'
    beta: np.ndarray  # (N, M+1) exact beta
    log_norm: float  # log of the sum over every valid assignment of prod_i eta_i(a_i)
    n_hypotheses: int  # the number of valid assignments with a finite log weight


def empty_tracks(T, J, d):
    """``T`` empty track slots of ``J`` empty components in ``d`` dimensions."""
    return Tracks(
        r=np.zeros(T),
        labels=-np.ones((T, 2), dtype=np.int64),
        mask=np.zeros(T, dtype=bool),
        w=np.zeros((T, J)),
        m=np.zeros((T, J, d)),
        P=np.tile(np.eye(d), (T, J, 1, 1)),
        cmask=np.zeros((T, J), dtype=bool),
    )


def gaussian_logpdf(z, mu, S):
    """``log N(z; mu, S)`` by the Cholesky factor of ``S``."""
    L = np.linalg.cholesky(S)
    x = np.linalg.solve(L, z - mu)
    n = len(z)
    return float(-0.5 * (n * np.log(2 * np.pi) + x @ x) - np.sum(np.log(np.diag(L))))


def kf_update(m, P, z, H, R):
    """``(m', P', q)``: ``S = H P H^T + R``, ``K = P H^T S^-1``, ``m' = m + K (z - H m)``,
    ``P' = (I - K H) P`` symmetrised, ``q = N(z; H m, S)``."""
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T  # S symmetric: (S^-1 H P)^T = P H^T S^-1
    m_new = m + K @ (z - H @ m)
    P_new = (np.eye(len(m)) - K @ H) @ P
    P_new = 0.5 * (P_new + P_new.T)
    return m_new, P_new, float(np.exp(gaussian_logpdf(z, H @ m, S)))


# --------------------------------------------------------------------------------------------- predict
def predict(tracks, F, Q, p_s, birth_w, birth_m, birth_P, birth_mask, step):
    """The LMB prediction at time ``step``: ``T`` survivors then ``B`` births, ``N = T + B`` slots.

    Args:
        tracks: the posterior at ``step - 1`` (``T`` slots of ``J`` components).
        birth_w, birth_m, birth_P, birth_mask: the birth mixture, ``(B,)``, ``(B, d)``, ``(B, d, d)``,
            ``(B,)``; live slot ``b`` is a track with ``r = birth_w[b]`` and label ``(step, b)``.
    """
    F, Q = np.asarray(F, float), np.asarray(Q, float)
    T, J, d = tracks.m.shape
    birth_w = np.asarray(birth_w, float)
    birth_m = np.asarray(birth_m, float)
    birth_P = np.asarray(birth_P, float)
    birth_mask = np.asarray(birth_mask, bool)
    B = len(birth_w)
    out = empty_tracks(T + B, J, d)
    for i in range(T):
        if not tracks.mask[i]:
            continue
        out.r[i] = p_s * tracks.r[i]
        out.labels[i] = tracks.labels[i]
        out.mask[i] = True
        for c in range(J):
            if not tracks.cmask[i, c]:
                continue
            out.w[i, c] = tracks.w[i, c]
            out.m[i, c] = F @ tracks.m[i, c]
            out.P[i, c] = F @ tracks.P[i, c] @ F.T + Q
            out.cmask[i, c] = True
    for b in range(B):
        if not birth_mask[b]:
            continue
        if not 0.0 <= birth_w[b] <= 1.0:
            raise ValueError(f"birth weight {birth_w[b]} of slot {b} is not an existence probability")
        i = T + b
        out.r[i] = birth_w[b]
        out.labels[i] = (step, b)
        out.mask[i] = True
        out.w[i, 0] = 1.0
        out.m[i, 0] = birth_m[b]
        out.P[i, 0] = birth_P[b]
        out.cmask[i, 0] = True
    return out


# ------------------------------------------------------------------------------------ update: costs
def kf_terms(tracks, Z, H, R):
    """Step 1: the KF update of every live component with every present measurement.

    Returns:
        ``(m_upd (N, J, M, d), P_upd (N, J, M, d, d), q (N, J, M), present (M,))``; entries of empty
        components or absent measurements are ``0`` (means, ``q``) and the identity (covariances).
    """
    H, R = np.asarray(H, float), np.asarray(R, float)
    N, J, d = tracks.m.shape
    Z = np.asarray(Z, float).reshape(-1, H.shape[0])
    M = Z.shape[0]
    present = np.array([not np.any(np.isnan(Z[j])) for j in range(M)], dtype=bool)
    m_upd = np.zeros((N, J, M, d))
    P_upd = np.tile(np.eye(d), (N, J, M, 1, 1))
    q = np.zeros((N, J, M))
    for i in range(N):
        if not tracks.mask[i]:
            continue
        for c in range(J):
            if not tracks.cmask[i, c]:
                continue
            for j in range(M):
                if present[j]:
                    m_upd[i, c, j], P_upd[i, c, j], q[i, c, j] = kf_update(
                        tracks.m[i, c], tracks.P[i, c], Z[j], H, R
                    )
    return m_upd, P_upd, q, present


def _log(x):
    with np.errstate(divide="ignore"):
        return float(np.log(x)) if x > 0 else NEG_INF


def _track_likelihood(tracks, q, i, j):
    """``sum_c w_ic q_icj`` over the live components of track ``i``, in component order."""
    s = 0.0
    for c in range(tracks.w.shape[1]):
        if tracks.cmask[i, c]:
            s += tracks.w[i, c] * q[i, c, j]
    return s


def log_eta_from_q(tracks, q, present, p_d, clutter_rate, clutter_density):
    """Step 2: the ``(N, M+2)`` joint costs ``log eta_i(a)`` from the detection likelihoods ``q``."""
    N, J, M = q.shape
    kappa = clutter_rate * clutter_density
    out = np.full((N, M + 2), NEG_INF)
    for i in range(N):
        if not tracks.mask[i]:
            out[i, 0] = 0.0
            continue
        r = tracks.r[i]
        out[i, 0] = _log(1.0 - r)
        out[i, 1] = _log(r * (1.0 - p_d))
        for j in range(M):
            if not present[j]:
                continue
            out[i, 2 + j] = _log(r * p_d * _track_likelihood(tracks, q, i, j) / kappa)
    return out


def log_eta(tracks, Z, H, R, p_d, clutter_rate, clutter_density):
    """The ``(N, M+2)`` joint costs of step 2 for the predicted ``tracks`` and the measurements ``Z``."""
    _, _, q, present = kf_terms(tracks, Z, H, R)
    return log_eta_from_q(tracks, q, present, p_d, clutter_rate, clutter_density)


# ----------------------------------------------------------------------------------- update: Gibbs
def gibbs(log_eta, start, uniforms):
    """Step 3: ``G = len(uniforms) + 1`` rows of the Gibbs sampler, ``(G, N)`` int.

    Args:
        log_eta: ``(N, M+2)`` the joint costs.
        start: ``(N,)`` bool, the live tracks: row 0 has ``gamma_i = 1`` for them, ``0`` otherwise.
        uniforms: ``(G - 1, N)`` in ``[0, 1)``; ``uniforms[g - 1, i]`` draws track ``i`` of row ``g``.
    """
    log_eta = np.asarray(log_eta, float)
    uniforms = np.asarray(uniforms, float)
    N, A = log_eta.shape
    G = uniforms.shape[0] + 1
    gamma = [1 if start[i] else 0 for i in range(N)]
    rows = [list(gamma)]
    for g in range(1, G):
        for i in range(N):
            l = []
            for a in range(A):
                taken = a >= 2 and any(gamma[k] == a for k in range(N) if k != i)
                l.append(NEG_INF if taken else log_eta[i, a])
            top = max(l)
            if top == NEG_INF:
                continue
            cum, total = [], 0.0
            for a in range(A):
                total += np.exp(l[a] - top)
                cum.append(total)
            threshold = uniforms[g - 1, i] * cum[A - 1]
            for a in range(A):
                if cum[a] > threshold:
                    gamma[i] = a
                    break
        rows.append(list(gamma))
    return np.array(rows, dtype=np.int64).reshape(G, N)


def unique_rows(samples):
    """Step 4: ``(G,)`` bool, row ``g`` kept iff no earlier row equals it."""
    G = samples.shape[0]
    kept = np.zeros(G, dtype=bool)
    seen = set()  # the rows met so far (as tuples): equal to comparing with every earlier row
    for g in range(G):
        row = tuple(int(a) for a in samples[g])
        kept[g] = row not in seen
        seen.add(row)
    return kept


def _logsumexp(x):
    if len(x) == 0:
        return NEG_INF
    top = max(x)
    if top == NEG_INF:
        return NEG_INF
    s = 0.0
    for v in x:
        s += np.exp(v - top)
    return float(top + np.log(s))


def hypothesis_weights(log_eta, samples, kept):
    """Steps 4-5: ``(weights (G,), r' (N,), beta (N, M+1), log_norm)`` of the kept rows.

    ``log_norm = log sum_{kept g} exp(sum_i log eta_i(gamma_gi))``.
    """
    G, N = samples.shape
    A = log_eta.shape[1]
    logW = np.full(G, NEG_INF)
    for g in range(G):
        if kept[g]:
            s = 0.0
            for i in range(N):
                s += log_eta[i, samples[g, i]]
            logW[g] = s
    log_norm = _logsumexp([logW[g] for g in range(G) if kept[g]])
    weights = np.zeros(G)
    if log_norm > NEG_INF:
        for g in range(G):
            if kept[g] and logW[g] > NEG_INF:
                weights[g] = np.exp(logW[g] - log_norm)
    r = np.zeros(N)
    beta = np.zeros((N, A - 1))
    for g in range(G):
        if not kept[g]:
            continue
        for i in range(N):
            a = samples[g, i]
            if a >= 1:
                r[i] += weights[g]
                beta[i, a - 1] += weights[g]
    return weights, r, beta, log_norm


# ----------------------------------------------------------------------------------- update: spatial
def _posterior_track(tracks, i, r_i, beta_i, m_upd, P_upd, q, present, n_components, component_threshold):
    """Steps 6-7 for track ``i``: ``(w (J',), m (J', d), P (J', d, d), cmask (J',))``."""
    _, J, d = tracks.m.shape
    M = len(present)
    # step 6: the (1 + M) J layout, flat slot b * J + c
    cand = []  # (weight, flat slot, mean, cov)
    for c in range(J):
        if tracks.cmask[i, c]:
            cand.append((beta_i[0] / r_i * tracks.w[i, c], c, tracks.m[i, c], tracks.P[i, c]))
    for j in range(M):
        if not present[j]:
            continue
        s = _track_likelihood(tracks, q, i, j)
        for c in range(J):
            if not tracks.cmask[i, c]:
                continue
            wt = beta_i[1 + j] / r_i * tracks.w[i, c] * q[i, c, j] / s if s > 0 else 0.0
            cand.append((wt, (1 + j) * J + c, m_upd[i, c, j], P_upd[i, c, j]))
    # step 7: threshold (strict), the J' heaviest (ties: lower flat slot), renormalise
    order = sorted(cand, key=lambda t: (-t[0], t[1]))
    keep = [t for t in order if not t[0] < component_threshold][:n_components]
    if not keep:
        keep = order[:1]
    w = np.zeros(n_components)
    m = np.zeros((n_components, d))
    P = np.tile(np.eye(d), (n_components, 1, 1))
    cmask = np.zeros(n_components, dtype=bool)
    total = 0.0
    for t in keep:
        total += t[0]
    for k, t in enumerate(keep):
        w[k] = t[0] / total if total > 0 else 1.0 / len(keep)
        m[k], P[k], cmask[k] = t[2], t[3], True
    return w, m, P, cmask


def update(
    tracks,
    Z,
    H,
    R,
    p_d,
    clutter_rate,
    clutter_density,
    uniforms,
    *,
    n_tracks,
    n_components,
    existence_threshold,
    component_threshold,
):
    """One GM-LMB update (spec steps 1-9) of the ``N`` predicted ``tracks`` with the padded ``Z (M, n_z)``.

    Args:
        uniforms: ``(G - 1, N)`` in ``[0, 1)``, the draws of the Gibbs sampler (``G`` rows).
        n_tracks, n_components: the capacity ``T`` and components per track ``J`` of the posterior.

    Returns:
        An :class:`UpdateResult`.
    """
    N, J, d = tracks.m.shape
    m_upd, P_upd, q, present = kf_terms(tracks, Z, H, R)
    L = log_eta_from_q(tracks, q, present, p_d, clutter_rate, clutter_density)
    samples = gibbs(L, tracks.mask, uniforms)
    kept = unique_rows(samples)
    weights, r_post, beta, log_norm = hypothesis_weights(L, samples, kept)

    # steps 6-7: every predicted track's posterior (N slots)
    full = empty_tracks(N, n_components, d)
    for i in range(N):
        if not tracks.mask[i] or not r_post[i] > 0:
            continue
        w, m, P, cm = _posterior_track(
            tracks, i, r_post[i], beta[i], m_upd, P_upd, q, present, n_components, component_threshold
        )
        full.r[i] = r_post[i]
        full.labels[i] = tracks.labels[i]
        full.mask[i] = True
        full.w[i], full.m[i], full.P[i], full.cmask[i] = w, m, P, cm

    # step 8: existence threshold (strict), the n_tracks largest r' in their original order
    cand = [i for i in range(N) if full.mask[i] and not full.r[i] < existence_threshold]
    best = sorted(cand, key=lambda i: (-full.r[i], i))[:n_tracks]
    chosen = sorted(best)
    overflow = len(cand) > n_tracks
    post = empty_tracks(n_tracks, n_components, d)
    for k, i in enumerate(chosen):
        for name in Tracks._fields:
            getattr(post, name)[k] = getattr(full, name)[i]

    # step 9
    m_z = int(np.sum(present))
    kappa = clutter_rate * clutter_density
    loglik = log_norm - clutter_rate + m_z * np.log(kappa)
    return UpdateResult(post, samples, kept, weights, r_post, beta, float(loglik), bool(overflow), L)


# ------------------------------------------------------------------------------------------- extract
def cardinality_pmf(r, mask, n_max=None):
    """The Poisson-binomial pmf of the live ``r``'s, ``n = 0 .. n_max`` (default: ``len(r)``), by
    convolving the Bernoulli pmfs ``[1 - r_i, r_i]`` in slot order."""
    n_max = len(r) if n_max is None else n_max
    rho = np.zeros(n_max + 1)
    rho[0] = 1.0
    for i in range(len(r)):
        if not mask[i]:
            continue
        new = np.zeros(n_max + 1)
        for n in range(n_max + 1):
            new[n] = rho[n] * (1.0 - r[i])
            if n >= 1:
                new[n] += rho[n - 1] * r[i]
        rho = new
    return rho


def extract(tracks, max_estimates):
    """The MAP cardinality ``n_hat`` (smallest on ties) and the slot-0 means of the ``n_hat`` tracks with
    the largest ``r`` (ties: lower slot first), in decreasing ``r``, padded to ``max_estimates`` rows."""
    T, _, d = tracks.m.shape
    rho = cardinality_pmf(tracks.r, tracks.mask, T)
    n_hat = 0
    for n in range(1, T + 1):
        if rho[n] > rho[n_hat]:
            n_hat = n
    live = [i for i in range(T) if tracks.mask[i]]
    order = sorted(live, key=lambda i: (-tracks.r[i], i))[:n_hat]
    states = np.zeros((max_estimates, d))
    labels = -np.ones((max_estimates, 2), dtype=np.int64)
    mask = np.zeros(max_estimates, dtype=bool)
    for k, i in enumerate(order[:max_estimates]):
        states[k] = tracks.m[i, 0]
        labels[k] = tracks.labels[i]
        mask[k] = True
    return Estimates(states, labels, mask, int(n_hat))


# ------------------------------------------------------------------------------------------ brute force
def exact_marginals(log_eta):
    """The exact ``r'``, ``beta`` and log normaliser of the costs ``log_eta (N, M+2)``, by enumerating
    every joint assignment: each track picks ``a`` in ``0 .. M+1`` and no detection ``a >= 2`` is picked
    twice. Weight ``prod_i eta_i(a_i)``. Keep ``N`` and ``M`` tiny (``(M + 2)^N`` assignments)."""
    log_eta = np.asarray(log_eta, float)
    N, A = log_eta.shape
    hyps, logw = [], []
    for a in itertools.product(range(A), repeat=N):
        det = [x for x in a if x >= 2]
        if len(det) != len(set(det)):
            continue
        s = 0.0
        for i in range(N):
            s += log_eta[i, a[i]]
        if s > NEG_INF:
            hyps.append(a)
            logw.append(s)
    log_norm = _logsumexp(logw)
    r = np.zeros(N)
    beta = np.zeros((N, A - 1))
    for a, lw in zip(hyps, logw):
        w = np.exp(lw - log_norm)
        for i in range(N):
            if a[i] >= 1:
                r[i] += w
                beta[i, a[i] - 1] += w
    return Exact(r, beta, float(log_norm), len(hyps))


# ---------------------------------------------------------------------------------------------- run
def run(
    tracks0,
    Zs,
    uniforms_per_step,
    F,
    Q,
    H,
    R,
    *,
    p_s,
    p_d,
    clutter_rate,
    clutter_density,
    birth_w,
    birth_m,
    birth_P,
    birth_mask=None,
    n_tracks,
    n_components,
    existence_threshold=1e-3,
    component_threshold=1e-5,
    max_estimates=None,
):
    """Predict / update / extract over the measurement sets ``Zs`` (steps ``k = 1, 2, ...``).

    Args:
        tracks0: the tracks at time 0 (``n_tracks`` slots of ``n_components`` components).
        uniforms_per_step: per step, ``(G - 1, n_tracks + B)`` uniforms for the Gibbs sampler.

    Returns:
        One dict per step: ``predicted`` (:class:`Tracks`), ``update`` (:class:`UpdateResult`),
        ``tracks`` (the posterior), ``estimates`` (:class:`Estimates`) and ``loglik``.
    """
    birth_mask = np.ones(len(birth_w), dtype=bool) if birth_mask is None else birth_mask
    max_estimates = n_tracks if max_estimates is None else max_estimates
    tracks = tracks0
    out = []
    for k, (Z, u) in enumerate(zip(Zs, uniforms_per_step), start=1):
        pred = predict(tracks, F, Q, p_s, birth_w, birth_m, birth_P, birth_mask, k)
        res = update(
            pred,
            Z,
            H,
            R,
            p_d,
            clutter_rate,
            clutter_density,
            u,
            n_tracks=n_tracks,
            n_components=n_components,
            existence_threshold=existence_threshold,
            component_threshold=component_threshold,
        )
        tracks = res.tracks
        est = extract(tracks, max_estimates)
        out.append(dict(predicted=pred, update=res, tracks=tracks, estimates=est, loglik=res.loglik))
    return out
