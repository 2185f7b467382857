"""Plain NumPy ISE between two mixtures: the per-pair loop a user would otherwise write.

Straight from seed 000 eqs 31 and 35: ISE = Σ_ij a_i a_j N(m_i; m_j, P_i + P_j)
- 2 Σ_ij a_i b_j N(m_i; m_j, P_i + P_j) + Σ_ij b_i b_j N(m_i; m_j, P_i + P_j).
"""

from __future__ import annotations

import numpy as np


def _gauss(x, m, P):
    d = x.shape[0]
    diff = x - m
    L = np.linalg.cholesky(P)
    r = np.linalg.solve(L, diff)
    return np.exp(-0.5 * r @ r - np.log(np.diag(L)).sum() - 0.5 * d * np.log(2 * np.pi))


def cross_term(wa, ma, Pa, wb, mb, Pb):
    """Σ_i Σ_j wa_i wb_j N(ma_i; mb_j, Pa_i + Pb_j) with explicit loops."""
    total = 0.0
    for i in range(len(wa)):
        for j in range(len(wb)):
            total += wa[i] * wb[j] * _gauss(ma[i], mb[j], Pa[i] + Pb[j])
    return total


def ise(wa, ma, Pa, wb, mb, Pb):
    """Integrated squared error between two unpadded mixtures (weights, means (K, d), covs (K, d, d))."""
    return (
        cross_term(wa, ma, Pa, wa, ma, Pa)
        - 2.0 * cross_term(wa, ma, Pa, wb, mb, Pb)
        + cross_term(wb, mb, Pb, wb, mb, Pb)
    )


def ise_vectorized(wa, ma, Pa, wb, mb, Pb):
    """The same ISE with NumPy broadcasting over component pairs (a stronger baseline)."""

    def term(w1, m1, P1, w2, m2, P2):
        S = P1[:, None] + P2[None, :]
        diff = m1[:, None] - m2[None, :]
        sol = np.linalg.solve(S, diff[..., None])[..., 0]
        quad = np.einsum("ijk,ijk->ij", diff, sol)
        _, logdet = np.linalg.slogdet(S)
        d = m1.shape[1]
        vals = np.exp(-0.5 * quad - 0.5 * logdet - 0.5 * d * np.log(2 * np.pi))
        return w1 @ vals @ w2

    return term(wa, ma, Pa, wa, ma, Pa) - 2 * term(wa, ma, Pa, wb, mb, Pb) + term(wb, mb, Pb, wb, mb, Pb)
