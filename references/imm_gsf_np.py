"""Plain NumPy IMM with Gaussian-sum model-conditioned filters, one run at a time.

The per-run loop a user would otherwise write for seed 003 §4.2 (the reference of
``gmjax.filters.imm.build_imm_gsf`` in ``benchmarks/bench_seed003_tracking.py``). For every step:
mixing ``mu_{i|j} = p_ij mu_i / c_j`` of the model-conditioned mixtures (a mixture of mixtures,
nothing collapsed), each model's EKF-based GSF step (:func:`gsf_np.gsf_step`), the model
probabilities ``mu_j ∝ c_j p(z | j)`` and a reduction of every model's updated mixture.
Mixtures are ``(w, m, P)`` tuples of live components only.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from references import gsf_np

Mixture = tuple[np.ndarray, np.ndarray, np.ndarray]


def run_imm_gsf(
    prior: Mixture,
    zs: np.ndarray,
    Fs: Sequence[np.ndarray],
    H: np.ndarray,
    q: Mixture,
    r: Mixture,
    trans: np.ndarray,
    reducer: Callable[[Mixture], Mixture],
    mu0: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Filter ``zs (T, m)`` with linear models ``x' = F_j x + v``, ``z = H x + w``.

    Returns:
        ``(estimates (T, d), model_probs (T, M))``; the estimate is the mean of
        ``sum_j mu_j p_j`` over the updated (pre-reduction) mixtures.
    """
    M = len(Fs)
    mu = np.full(M, 1.0 / M) if mu0 is None else np.asarray(mu0, float)
    posts = [prior] * M
    ests, probs = [], []
    for k, z in enumerate(zs):
        c = trans.T @ mu  # c_j = sum_i p_ij mu_i
        full, logliks = [], []
        for j in range(M):
            ws, ms, Ps = [], [], []
            for i in range(M):
                mix_ij = trans[i, j] * mu[i] / c[j]
                if mix_ij > 0:
                    ws.append(mix_ij * posts[i][0])
                    ms.append(posts[i][1])
                    Ps.append(posts[i][2])
            mixed = (np.concatenate(ws), np.concatenate(ms), np.concatenate(Ps))
            upd, ll = gsf_np.gsf_step(
                mixed,
                z,
                k + 1,
                lambda x, t, F=Fs[j]: F @ x,
                lambda x, t: H @ x,
                lambda x, t, F=Fs[j]: F,
                lambda x, t: H,
                q,
                r,
            )
            full.append(upd)
            logliks.append(ll)
        logliks = np.array(logliks)
        a = np.log(c) + logliks
        mu = np.exp(a - a.max())
        mu /= mu.sum()
        means = [gsf_np.moments(f)[0] for f in full]
        ests.append(sum(mu[j] * means[j] for j in range(M)))
        probs.append(mu.copy())
        posts = [reducer(f) for f in full]
    return np.array(ests), np.array(probs)
