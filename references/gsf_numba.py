"""The R-GSF (Gaussian sum filter with EKF components and Runnalls reduction) as a compiled per-run
loop (numba): the speed baseline for gmjax's ``jit(vmap(run(build_gsf(model, "ekf", Runnalls(K),
capacity=K))))``.

What a user who wants the whole filter fast without JAX would write: one plain loop over the time
steps of one run, compiled with numba's ``@njit``, and a batch driver that runs the runs in parallel
with ``numba.prange`` (``parallel=True``). Each step, for the posterior's ``K`` slots, ``L``
process-noise and ``J`` measurement-noise components (seed 000 eqs 4-18):

* **predict**: every live component ``i`` x every noise component ``l`` (child ``i*L + l``):
  ``m' = f(m_i, t) + q_l``, ``P' = sym(F P_i F^T + Q_l)`` with ``F`` the Jacobian at ``m_i``, weight
  ``exp(log w_i + log gamma_l)``;
* **update**: every predicted component x every measurement-noise component ``j`` (child
  ``c*J + j``): ``z_hat = h(m_c, t) + r_j``, ``S = sym(H P H^T + R_j)`` with ``H`` the Jacobian at
  ``m_c``, its Cholesky factor, ``K = P H^T S^-1`` by two triangular solves, ``m+ = m + K y``,
  Joseph form ``P+ = sym((I - K H) P (I - K H)^T + K R_j K^T)``, ``log N(y; 0, S)``; weights
  ``exp(log w_c + log beta_j + log N - logsumexp(...))`` (if every likelihood underflows, the
  predicted weights are kept, as gmjax);
* **estimate**: the moments of the ``K L J`` updated components (eqs 17-18), before reduction;
* **reduce**: Runnalls' greedy merging down to ``K`` (``references/reduction_numba._runnalls_core``:
  cached log-determinants, one cost row/column per merge, row minima cached), then the live slots
  ordered heaviest first (ties: the lower slot), as gmjax's ``fit_capacity`` (``top_k``) stores them.

It follows gmjax's arithmetic (``gmjax/filters/gsf.py``, ``_linearized.py``, ``gaussian.py``,
``reduction/_greedy.py``) and its merge order: the same child numbering, log-domain weights, the
unrolled Cholesky and triangular solves in gmjax's order, the Jacobians as ``jax.jacfwd`` evaluates
them (e.g. ``(2 x0) (0.5 / r)`` for the range's derivative), and the same slot layout before every
Runnalls call, so the merge sequence, and the estimates, equal gmjax's to rounding.

The model functions are hand-written for two systems (``system``):

* ``JUMP`` (0): seed 000's scalar measurement-jump system (``gmjax.scenarios.jump_system``):
  ``f = x/2 + 25 x / (1 + x^2) + 8 cos(1.2 (t - 1))``, ``h = x^2 / 20`` for ``t <= theta[0]`` (the
  switch step, 80) else ``3 x - 4``;
* ``RANGE_BEARING`` (1): seed 000 Table 8's 4-D CV range-bearing system
  (``gmjax.scenarios.glint_range_bearing.range_bearing``): ``f = F x`` with the sampling period
  ``theta[0]`` (0.01 s), ``h = (sqrt(x0^2 + x2^2), atan2(x2, x0))``. The scenario declares no angle
  dimension, so gmjax does not wrap the bearing innovation, and neither does this loop.

Omitted (what gmjax does and a baseline would skip): the flags (repaired, overflow, degenerate,
missing), covariance repair (the jitter of ``gaussian.safe_cholesky`` / ``repair_spd``: a
non-positive-definite ``S`` gives NaN here), predict-only steps on a non-finite measurement,
overflow handling of the reducer (Runnalls always ends at ``<= K`` live slots), the log-likelihood
and every other ``StepInfo`` field, and noise mixtures with padded slots (pass only live noise
components).

Inputs are float64 arrays: the prior padded to the capacity ``K`` (weights ``(K,)``, means
``(K, d)``, covariances ``(K, d, d)``, mask ``(K,)``; normalised here as gmjax's ``check_prior``),
the noises' weights / means / covariances, the measurements ``zs`` ``(T, mz)`` (batch: ``(B, T, mz)``)
and the times ``ts`` ``(T,)`` of ``gmjax.models.base.simulate``. Outputs: the per-step estimate means
``(T, d)`` and covariances ``(T, d, d)`` (batch: leading ``B``).

Without numba the module still imports and runs as plain Python (``njit`` is then the identity and
``prange`` is ``range``); with numba, ``gsf_run.py_func`` / ``gsf_batch.py_func`` are the same code
run by the interpreter (the helpers are ``register_jitable``), which is what the default tests use.
This module does not import gmjax.
"""

from __future__ import annotations

import math

import numpy as np

# numba's decorators, or plain-Python stand-ins without numba: reduction_numba's (one fallback)
try:  # as the tests and benchmarks import it (the repository root on sys.path)
    from references.reduction_numba import (
        HAVE_NUMBA,
        _cholesky_at,
        _runnalls_core,
        njit,
        prange,
        register_jitable,
    )
except ImportError:  # pragma: no cover - run from inside references/
    from reduction_numba import HAVE_NUMBA, _cholesky_at, _runnalls_core, njit, prange, register_jitable

__all__ = [
    "HAVE_NUMBA",
    "JUMP",
    "RANGE_BEARING",
    "JUMP_THETA",
    "RANGE_BEARING_THETA",
    "gsf_run",
    "gsf_batch",
]

JUMP = 0
RANGE_BEARING = 1
JUMP_THETA = np.array([80.0])  # switch_step of jump_system()
RANGE_BEARING_THETA = np.array([0.01])  # dt of range_bearing()

_LOG_2PI = 1.8378770664093453
_JIT = {"error_model": "numpy"}  # inf / nan on division by zero, no Python exception checks


# ----------------------------------------------------------------------------- the two models


@register_jitable
def _f_jac(system, theta, m, k, t, fx, F):
    """``f(m[k], t)`` into ``fx (d,)`` and its Jacobian into ``F (d, d)`` (as ``jax.jacfwd`` of the
    scenario's ``f`` evaluates it; the range-bearing model's Jacobian is its given matrix)."""
    if system == JUMP:
        x = m[k, 0]
        b = 1.0 + x * x
        fx[0] = x / 2.0 + 25.0 * x / b + 8.0 * math.cos(1.2 * (t - 1.0))
        # jvp of x/2 + (25 x) / (1 + x^2): 1/2 + [25 / b + (-(2 x) (25 x)) b^-2]
        F[0, 0] = 0.5 + (25.0 / b + (-(2.0 * x) * (25.0 * x)) * (1.0 / (b * b)))
    else:
        dt = theta[0]
        d = m.shape[1]
        for a in range(d):
            for c in range(d):
                F[a, c] = 0.0
            F[a, a] = 1.0
        F[0, 1] = dt
        F[2, 3] = dt
        for a in range(d):
            s = 0.0
            for c in range(d):
                s += F[a, c] * m[k, c]
            fx[a] = s


@register_jitable
def _h_jac(system, theta, m, k, t, hx, H):
    """``h(m[k], t)`` into ``hx (mz,)`` and its Jacobian into ``H (mz, d)`` (``jax.jacfwd``'s values)."""
    if system == JUMP:
        x = m[k, 0]
        if t <= theta[0]:
            hx[0] = x * x / 20.0
            H[0, 0] = (2.0 * x) / 20.0
        else:
            hx[0] = 3.0 * x - 4.0
            H[0, 0] = 3.0
    else:
        x0 = m[k, 0]
        x2 = m[k, 2]
        r = math.sqrt(x0 * x0 + x2 * x2)
        hx[0] = r
        hx[1] = math.atan2(x2, x0)
        den = x2 * x2 + x0 * x0  # atan2's jvp: square(y) + square(x)
        d = m.shape[1]
        for c in range(d):
            H[0, c] = 0.0
            H[1, c] = 0.0
        H[0, 0] = (2.0 * x0) * (0.5 / r)
        H[0, 2] = (2.0 * x2) * (0.5 / r)
        H[1, 0] = -x2 / den
        H[1, 2] = x0 / den


# ----------------------------------------------------------------------------- helpers


@register_jitable
def _logsumexp(a, n, mask):
    """``log sum exp a[:n]`` over ``mask`` (jax's form: ``log(sum exp(a - max)) + max``, a non-finite
    max replaced by 0)."""
    amax = -np.inf
    for k in range(n):
        if mask[k] and a[k] > amax:
            amax = a[k]
    if not math.isfinite(amax):
        amax = 0.0
    s = 0.0
    for k in range(n):
        if mask[k]:
            s += math.exp(a[k] - amax)
    return math.log(s) + amax


@register_jitable
def _noise_log_weights(w):
    """gmjax's ``_noise_log_weights``: ``log w - logsumexp(log w)`` (every component live)."""
    n = w.shape[0]
    lw = np.empty(n)
    live = np.ones(n, np.bool_)
    for k in range(n):
        lw[k] = math.log(w[k]) if w[k] > 0 else -np.inf
    lse = _logsumexp(lw, n, live)
    for k in range(n):
        lw[k] = lw[k] - lse
    return lw


@register_jitable
def _moments(w, m, P, mask, out_m, out_P, t, dev):
    """gmjax's ``mixture.moments`` of the live slots into ``out_m[t]``, ``out_P[t]``."""
    n, d = m.shape
    total = 0.0
    for k in range(n):
        if mask[k]:
            total += w[k]
    for a in range(d):
        s = 0.0
        for k in range(n):
            if mask[k]:
                s += (w[k] / total) * m[k, a]
        out_m[t, a] = s
    for a in range(d):
        for b in range(d):
            spread = 0.0
            within = 0.0
            for k in range(n):
                if mask[k]:
                    wk = w[k] / total
                    spread += wk * (m[k, a] - out_m[t, a]) * (m[k, b] - out_m[t, b])
                    within += wk * P[k, a, b]
            dev[a, b] = within + spread
    for a in range(d):
        for b in range(d):
            out_P[t, a, b] = 0.5 * (dev[a, b] + dev[b, a])


# ----------------------------------------------------------------------------- one run


@register_jitable
def _gsf_core(
    system, theta, prior_w, prior_m, prior_P, prior_mask, q_w, q_m, q_P, r_w, r_m, r_P, zs, ts, out_m, out_P
):
    """The R-GSF over one run (``zs (T, mz)``) into ``out_m (T, d)``, ``out_P (T, d, d)``."""
    K, d = prior_m.shape
    L = q_w.shape[0]
    J = r_w.shape[0]
    mz = zs.shape[1]
    T = zs.shape[0]
    KL = K * L
    KLJ = KL * J
    q_lw = _noise_log_weights(q_w)
    r_lw = _noise_log_weights(r_w)
    # posterior (K slots): the prior normalised (gmjax's check_prior)
    w = np.zeros(K)
    m = np.zeros((K, d))
    P = np.zeros((K, d, d))
    mask = np.zeros(K, np.bool_)
    total = 0.0
    for i in range(K):
        if prior_mask[i]:
            total += prior_w[i]
    for i in range(K):
        mask[i] = prior_mask[i]
        w[i] = prior_w[i] / total if prior_mask[i] else 0.0
        for a in range(d):
            m[i, a] = prior_m[i, a] if prior_mask[i] else 0.0
            for b in range(d):
                P[i, a, b] = prior_P[i, a, b] if prior_mask[i] else (1.0 if a == b else 0.0)
    # predicted (K L) and updated (K L J) components; dead slots (0, 0, I)
    pw = np.zeros(KL)
    pm = np.zeros((KL, d))
    pP = np.zeros((KL, d, d))
    pmask = np.zeros(KL, np.bool_)
    uw = np.zeros(KLJ)
    um = np.zeros((KLJ, d))
    uP = np.zeros((KLJ, d, d))
    umask = np.zeros(KLJ, np.bool_)
    log_prior = np.zeros(KLJ)
    log_w = np.zeros(KLJ)
    # scratch
    fx = np.zeros(d)
    F = np.zeros((d, d))
    FP = np.zeros((d, d))
    A = np.zeros((d, d))
    AP = np.zeros((d, d))
    C = np.zeros((d, d))
    hx = np.zeros(mz)
    H = np.zeros((mz, d))
    HP = np.zeros((mz, d))  # (P H^T)^T
    HPH = np.zeros((mz, mz))
    S = np.zeros((1, mz, mz))
    Lc = np.zeros((mz, mz))
    y = np.zeros(mz)
    r = np.zeros(mz)
    X = np.zeros((mz, d))  # K^T = S^-1 (P H^T)^T
    KR = np.zeros((d, mz))
    dev = np.zeros((d, d))
    # Runnalls' buffers (gmjax's default output capacity: the input's K L J)
    rw = np.zeros(KLJ)
    rm = np.zeros((KLJ, d))
    rP = np.zeros((KLJ, d, d))
    rmask = np.zeros(KLJ, np.bool_)
    rlab = np.zeros(KLJ, np.int64)
    merges = np.empty((max(KLJ - K, 0), 2), np.int64)
    taken = np.zeros(KLJ, np.bool_)
    for step in range(T):
        t = ts[step]
        # ---- predict: child i*L + l
        for i in range(K):
            if not mask[i]:
                for l in range(L):
                    c = i * L + l
                    pmask[c] = False
                    pw[c] = 0.0
                    for a in range(d):
                        pm[c, a] = 0.0
                        for b in range(d):
                            pP[c, a, b] = 1.0 if a == b else 0.0
                continue
            lwi = math.log(w[i]) if w[i] > 0 else -np.inf
            _f_jac(system, theta, m, i, t, fx, F)
            for a in range(d):
                for b in range(d):
                    s = 0.0
                    for k in range(d):
                        s += F[a, k] * P[i, k, b]
                    FP[a, b] = s
            for a in range(d):
                for b in range(d):
                    s = 0.0
                    for k in range(d):
                        s += FP[a, k] * F[b, k]
                    C[a, b] = s
            for l in range(L):
                c = i * L + l
                pmask[c] = True
                pw[c] = math.exp(lwi + q_lw[l])
                for a in range(d):
                    pm[c, a] = fx[a] + q_m[l, a]
                for a in range(d):
                    for b in range(d):
                        pP[c, a, b] = 0.5 * ((C[a, b] + q_P[l, a, b]) + (C[b, a] + q_P[l, b, a]))
        # ---- update: child c*J + j
        for c in range(KL):
            if not pmask[c]:
                for j in range(J):
                    u = c * J + j
                    umask[u] = False
                    log_prior[u] = -np.inf
                    log_w[u] = -np.inf
                continue
            lwc = math.log(pw[c]) if pw[c] > 0 else -np.inf
            _h_jac(system, theta, pm, c, t, hx, H)
            for a in range(mz):  # (P H^T)^T[a, b] = sum_k P[b, k] H[a, k]
                for b in range(d):
                    s = 0.0
                    for k in range(d):
                        s += pP[c, b, k] * H[a, k]
                    HP[a, b] = s
            for a in range(mz):  # (H P) H^T
                for b in range(mz):
                    s = 0.0
                    for k in range(d):
                        s2 = 0.0
                        for q in range(d):
                            s2 += H[a, q] * pP[c, q, k]
                        s += s2 * H[b, k]
                    HPH[a, b] = s
            for j in range(J):
                u = c * J + j
                umask[u] = True
                for a in range(mz):
                    for b in range(mz):
                        S[0, a, b] = 0.5 * ((HPH[a, b] + r_P[j, a, b]) + (HPH[b, a] + r_P[j, b, a]))
                _cholesky_at(S, 0, Lc)
                for a in range(mz):
                    y[a] = zs[step, a] - (hx[a] + r_m[j, a])
                # K^T = (L L^T)^-1 (P H^T)^T: forward then back substitution, column by column
                for b in range(d):
                    for a in range(mz):
                        acc = HP[a, b]
                        for k in range(a):
                            acc = acc - Lc[a, k] * X[k, b]
                        X[a, b] = acc / Lc[a, a]
                    for a in range(mz - 1, -1, -1):
                        acc = X[a, b]
                        for k in range(a + 1, mz):
                            acc = acc - Lc[k, a] * X[k, b]
                        X[a, b] = acc / Lc[a, a]
                for a in range(d):
                    s = 0.0
                    for k in range(mz):
                        s += X[k, a] * y[k]
                    um[u, a] = pm[c, a] + s
                for a in range(d):  # A = I - K H
                    for b in range(d):
                        s = 0.0
                        for k in range(mz):
                            s += X[k, a] * H[k, b]
                        A[a, b] = (1.0 if a == b else 0.0) - s
                for a in range(d):  # A P
                    for b in range(d):
                        s = 0.0
                        for k in range(d):
                            s += A[a, k] * pP[c, k, b]
                        AP[a, b] = s
                for a in range(d):  # K R
                    for b in range(mz):
                        s = 0.0
                        for k in range(mz):
                            s += X[k, a] * r_P[j, k, b]
                        KR[a, b] = s
                for a in range(d):  # (A P) A^T + (K R) K^T
                    for b in range(d):
                        s = 0.0
                        for k in range(d):
                            s += AP[a, k] * A[b, k]
                        s2 = 0.0
                        for k in range(mz):
                            s2 += KR[a, k] * X[k, b]
                        C[a, b] = s + s2
                for a in range(d):
                    for b in range(d):
                        uP[u, a, b] = 0.5 * (C[a, b] + C[b, a])
                # log N(y; 0, S) from the factor
                rr = 0.0
                ldl = 0.0
                for a in range(mz):
                    acc = y[a]
                    for k in range(a):
                        acc = acc - Lc[a, k] * r[k]
                    r[a] = acc / Lc[a, a]
                    rr += r[a] * r[a]
                    ldl += math.log(abs(Lc[a, a]))
                ll = -0.5 * (mz * _LOG_2PI + rr) - ldl
                log_prior[u] = lwc + r_lw[j]
                log_w[u] = log_prior[u] + ll
        lse = _logsumexp(log_w, KLJ, umask)
        if not math.isfinite(lse):  # every likelihood underflowed: keep the predicted weights
            for u in range(KLJ):
                log_w[u] = log_prior[u]
            lse = _logsumexp(log_prior, KLJ, umask)
        for u in range(KLJ):
            if umask[u]:
                uw[u] = math.exp(log_w[u] - lse)
            else:
                uw[u] = 0.0
                for a in range(d):
                    um[u, a] = 0.0
                    for b in range(d):
                        uP[u, a, b] = 1.0 if a == b else 0.0
        # ---- estimate: moments of the updated mixture
        _moments(uw, um, uP, umask, out_m, out_P, step, dev)
        # ---- reduce: Runnalls to K, then the live slots heaviest first (ties: the lower slot)
        _runnalls_core(uw, um, uP, umask, K, np.inf, rw, rm, rP, rmask, rlab, merges)
        for k in range(KLJ):
            taken[k] = False
        for p in range(K):
            best = -1
            for k in range(KLJ):
                if rmask[k] and not taken[k] and (best < 0 or rw[k] > rw[best]):
                    best = k
            if best < 0:
                mask[p] = False
                w[p] = 0.0
                for a in range(d):
                    m[p, a] = 0.0
                    for b in range(d):
                        P[p, a, b] = 1.0 if a == b else 0.0
                continue
            taken[best] = True
            mask[p] = True
            w[p] = rw[best]
            for a in range(d):
                m[p, a] = rm[best, a]
                for b in range(d):
                    P[p, a, b] = rP[best, a, b]


@njit(**_JIT)
def gsf_run(system, theta, prior_w, prior_m, prior_P, prior_mask, q_w, q_m, q_P, r_w, r_m, r_P, zs, ts):
    """The R-GSF over one run.

    Args:
        system: ``JUMP`` or ``RANGE_BEARING``; theta: its parameters (``JUMP_THETA``,
            ``RANGE_BEARING_THETA``).
        prior_w, prior_m, prior_P, prior_mask: the prior padded to the capacity ``K`` (``(K,)``,
            ``(K, d)``, ``(K, d, d)``, ``(K,)`` bool); Runnalls reduces to ``K``.
        q_w, q_m, q_P: the process-noise mixture (``(L,)``, ``(L, d)``, ``(L, d, d)``).
        r_w, r_m, r_P: the measurement-noise mixture (``(J,)``, ``(J, mz)``, ``(J, mz, mz)``).
        zs: ``(T, mz)`` measurements; ts: ``(T,)`` times (float64).

    Returns:
        ``(means (T, d), covs (T, d, d))``: the moments of each step's updated mixture.
    """
    T = zs.shape[0]
    d = prior_m.shape[1]
    out_m = np.zeros((T, d))
    out_P = np.zeros((T, d, d))
    _gsf_core(
        system,
        theta,
        prior_w,
        prior_m,
        prior_P,
        prior_mask,
        q_w,
        q_m,
        q_P,
        r_w,
        r_m,
        r_P,
        zs,
        ts,
        out_m,
        out_P,
    )
    return out_m, out_P


@njit(parallel=True, **_JIT)
def gsf_batch(system, theta, prior_w, prior_m, prior_P, prior_mask, q_w, q_m, q_P, r_w, r_m, r_P, zs, ts):
    """:func:`gsf_run` over ``zs (B, T, mz)`` (one prior, one time grid), runs in parallel
    (``prange``); the outputs gain the leading ``B`` axis."""
    B, T, _ = zs.shape
    d = prior_m.shape[1]
    out_m = np.zeros((B, T, d))
    out_P = np.zeros((B, T, d, d))
    for b in prange(B):
        _gsf_core(
            system,
            theta,
            prior_w,
            prior_m,
            prior_P,
            prior_mask,
            q_w,
            q_m,
            q_P,
            r_w,
            r_m,
            r_P,
            zs[b],
            ts,
            out_m[b],
            out_P[b],
        )
    return out_m, out_P
