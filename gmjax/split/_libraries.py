"""The 1-D splitting libraries ``N(0, 1) ~= sum_i w_i N(mu_i, sigma^2)``, built eagerly in NumPy, once.

:class:`~gmjax.split.SplitLibrary` holds one; :func:`~gmjax.split.gauss_hermite_library` (Horwood-Poore's
Gauss-Hermite library), :func:`~gmjax.split.uniform_library` (uniform spacing with L2-optimal weights,
seed 002 eqs 13-16) and :func:`~gmjax.split.principal_library` (seed 001's two-way split, eq 32) build
them, and :func:`~gmjax.split.library_l2_error` and :func:`~gmjax.split.library_moments` measure how well
one approximates ``N(0, 1)``. :mod:`gmjax.split` describes the libraries and how they split a Gaussian.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np

from gmjax._types import Array


class SplitLibrary(NamedTuple):
    """A 1-D splitting library ``N(0, 1) ~= sum_i w_i N(mu_i, sigma^2)`` (seed 002 eq 12).

    Attributes:
        weights: ``(M,)`` non-negative, summing to 1.
        means: ``(M,)`` component means ``mu_i``.
        sigma: ``()`` common component standard deviation ``0 < sigma < 1``.
    """

    weights: Array | np.ndarray
    means: Array | np.ndarray
    sigma: Array | np.ndarray

    @property
    def size(self) -> int:
        """``M``, the number of components (static)."""
        return int(np.shape(self.weights)[0])


# ----------------------------------------------------------------------------------------------
# Libraries (eager NumPy)
# ----------------------------------------------------------------------------------------------


def _check_sigma(sigma: float) -> float:
    sigma = float(sigma)
    if not (0.0 < sigma < 1.0) or not math.isfinite(sigma):
        raise ValueError(f"sigma: must satisfy 0 < sigma < 1, got {sigma}")
    return sigma


def _make_library(weights: np.ndarray, means: np.ndarray, sigma: float) -> SplitLibrary:
    return SplitLibrary(
        np.asarray(weights, np.float64), np.asarray(means, np.float64), np.asarray(sigma, np.float64)
    )


def gauss_hermite_library(num: int, sigma: float) -> SplitLibrary:
    """Horwood-Poore's Gauss-Hermite splitting library (seed 002 §III-A, first library).

    ``w_i`` are the Gauss-Hermite weights normalised to sum to 1 and ``mu_i = k z_i`` where ``z_i``
    are the nodes for ``N(0, 1)`` (``z_i = sqrt(2) eps_i`` with ``eps_i`` the roots of the physicists'
    Hermite polynomial, eq 36) and ``k = sqrt(1 - sigma^2)``, so that ``sigma^2 = 1 - k^2``. With the
    normalised nodes, the library's moments equal those of ``N(0, 1)`` up to order ``2 num - 1``.

    Args:
        num: ``M >= 1``, the number of components.
        sigma: component standard deviation, ``0 < sigma < 1``.

    Raises:
        ValueError: for ``num < 1`` or ``sigma`` outside ``(0, 1)``.
    """
    if int(num) != num or num < 1:
        raise ValueError(f"num: must be a positive integer, got {num}")
    sigma = _check_sigma(sigma)
    z, w = np.polynomial.hermite_e.hermegauss(int(num))
    w = w / w.sum()
    k = math.sqrt(1.0 - sigma * sigma)
    return _make_library(w, k * z, sigma)


def _l2_gram(means: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Quadratic form of eq 13: ``E(w) = c - 2 b^T w + w^T G w``."""
    diff = means[:, None] - means[None, :]
    s2 = 2.0 * sigma * sigma
    G = np.exp(-0.5 * diff**2 / s2) / math.sqrt(2.0 * math.pi * s2)
    v = 1.0 + sigma * sigma
    b = np.exp(-0.5 * means**2 / v) / math.sqrt(2.0 * math.pi * v)
    c = 1.0 / (2.0 * math.sqrt(math.pi))
    return G, b, c


def library_l2_error(library: SplitLibrary) -> float:
    """L2 distance of eq 13 between ``N(0, 1)`` and the library, ``E`` (not its root).

    Integrated on a fine uniform grid (the trapezoid rule is spectrally accurate for these smooth,
    fast-decaying integrands), which avoids the cancellation of the closed form ``c - 2 b^T w +
    w^T G w`` when ``E`` is near machine precision.
    """
    w = np.asarray(library.weights, np.float64)
    mu = np.asarray(library.means, np.float64)
    s = float(library.sigma)
    lo = min(-10.0, float(mu.min()) - 12.0 * s)
    hi = max(10.0, float(mu.max()) + 12.0 * s)
    n = int(min(200_001, max(20_001, 40 * (hi - lo) / s)))
    x = np.linspace(lo, hi, n)
    ref = np.exp(-0.5 * x**2) / math.sqrt(2.0 * math.pi)
    mix = np.zeros_like(x)
    for wi, mi in zip(w, mu):
        mix += wi * np.exp(-0.5 * ((x - mi) / s) ** 2) / (s * math.sqrt(2.0 * math.pi))
    return float(np.trapezoid((ref - mix) ** 2, x))


def library_moments(library: SplitLibrary, orders: Sequence[int]) -> np.ndarray:
    """Raw moments ``E[x^p]`` of the library mixture for each ``p`` in ``orders`` (closed form)."""
    w = np.asarray(library.weights, np.float64)
    mu = np.asarray(library.means, np.float64)
    s = float(library.sigma)
    out = []
    for p in orders:
        # E[(mu + s e)^p] = sum_j C(p, j) mu^(p-j) s^j E[e^j], E[e^j] = (j-1)!! for even j.
        tot = np.zeros_like(mu)
        for j in range(0, p + 1, 2):
            dfact = float(np.prod(np.arange(j - 1, 0, -2))) if j > 0 else 1.0
            tot = tot + math.comb(p, j) * mu ** (p - j) * s**j * dfact
        out.append(float(w @ tot))
    return np.asarray(out)


def _nnls_simplex(G: np.ndarray, b: np.ndarray, rho: float = 1e3) -> np.ndarray:
    """``argmin w^T G w - 2 b^T w`` s.t. ``w >= 0, sum w = 1`` (NNLS on a square root of ``G``).

    ``G`` is written as ``A^T A`` with ``A = diag(sqrt(lam)) V^T`` from its eigendecomposition (``G``
    is a Gram matrix of Gaussians, positive semi-definite but badly conditioned). The linear term
    becomes ``A^T c = b`` on the numerically non-null eigenspace, and the sum constraint is an extra
    row weighted by ``rho``. The solution is refined by a few active-set Newton steps and finally
    rescaled to sum to 1 exactly.
    """
    from scipy.optimize import nnls

    lam, V = np.linalg.eigh(G)
    keep = lam > lam.max() * 1e-15
    A = np.sqrt(lam[keep])[:, None] * V[:, keep].T
    c = (V[:, keep].T @ b) / np.sqrt(lam[keep])
    n = G.shape[0]
    A_aug = np.vstack([A, rho * np.ones((1, n))])
    c_aug = np.concatenate([c, [rho]])
    w, _ = nnls(A_aug, c_aug, maxiter=50 * n)
    # Polish: on the active set solve the equality-constrained QP exactly (KKT system).
    for _ in range(5):
        act = w > 0
        k = int(act.sum())
        K = np.zeros((k + 1, k + 1))
        K[:k, :k] = G[np.ix_(act, act)]
        K[:k, k] = 1.0
        K[k, :k] = 1.0
        rhs = np.concatenate([b[act], [1.0]])
        try:
            sol = np.linalg.lstsq(K, rhs, rcond=None)[0]
        except np.linalg.LinAlgError:  # pragma: no cover
            break
        if np.all(sol[:k] >= 0):
            w = np.zeros(n)
            w[act] = sol[:k]
            break
        # step towards the KKT point while staying feasible
        wa = np.zeros(n)
        wa[act] = sol[:k]
        d = wa - w
        neg = d < 0
        t = min(1.0, float(np.min(-w[neg] / d[neg]))) if neg.any() else 1.0
        w = np.maximum(w + t * d, 0.0)
        w[w < 1e-300] = 0.0
    return w / w.sum()


def uniform_library(sigma: float) -> SplitLibrary:
    """Horwood-Poore's uniform-spacing library with L2-optimal weights (seed 002 eqs 13-16).

    ``sigma_i = sigma`` (eq 14), ``mu_i = -m + sigma (i - 1)`` (eq 15), ``M = ceil(1 + 2 m / sigma)``
    (eq 16) with ``m = 6`` if ``sigma < 1/2`` else ``m = 4``. The weights minimise the closed-form
    L2 distance of eq 13 - a quadratic ``c - 2 b^T w + w^T G w`` with ``G_ij = N(mu_i; mu_j, 2 sigma^2)``
    and ``b_i = N(mu_i; 0, 1 + sigma^2)`` - subject to ``w >= 0`` and ``sum w = 1`` (eqs 10-11; the
    paper says only "a quadratic optimisation problem"; we keep the weights a valid mixture).
    Solved once with SciPy's NNLS on a square root of ``G`` plus an exact KKT polish.

    Args:
        sigma: component standard deviation, ``0 < sigma < 1`` (e.g. 1/4 gives ``M = 49``).

    Raises:
        ValueError: for ``sigma`` outside ``(0, 1)``.
    """
    sigma = _check_sigma(sigma)
    m = 6.0 if sigma < 0.5 else 4.0
    num = int(math.ceil(1.0 + 2.0 * m / sigma - 1e-9))
    means = -m + sigma * np.arange(num, dtype=np.float64)
    G, b, _ = _l2_gram(means, sigma)
    w = _nnls_simplex(G, b)
    return _make_library(w, means, sigma)


def principal_library(l: float = 0.5, w: float = 0.5) -> SplitLibrary:  # noqa: E741
    """Seed 001's two-way split (eq 32) as a library: means ``(+l, -l)``, weights ``(w, 1 - w)``.

    Applied along the principal axis ``sqrt(lambda) e_v`` it gives exactly eq 32:
    ``mu_{1,2} = mu +- l sqrt(lambda) e_v`` and ``Sigma_{1,2} = Sigma - l^2 lambda e_v e_v^T``
    (so ``sigma^2 = 1 - l^2``). For ``w != 1/2`` the split does not preserve the mean (as written in
    the paper).

    Raises:
        ValueError: unless ``0 < l < 1`` and ``0 < w < 1``.
    """
    if not (0.0 < float(l) < 1.0):
        raise ValueError(f"l: must satisfy 0 < l < 1, got {l}")
    if not (0.0 < float(w) < 1.0):
        raise ValueError(f"w: must satisfy 0 < w < 1, got {w}")
    return _make_library(np.array([w, 1.0 - w]), np.array([l, -l]), math.sqrt(1.0 - float(l) ** 2))
