"""Quadrature point sets for expectations under a Gaussian.

Every rule here is a :class:`SigmaPoints` for the standard normal ``N(0, I_d)``:

.. math:: \\int g(z) N(z; 0, I)\\,dz \\approx \\sum_i w_i\\, g(z_i),

and is mapped to ``N(mu, P)`` through ``x_i = mu + L z_i`` with ``P = L L^T`` (seed 002 eq 38;
:func:`transform`). Rules are built eagerly in NumPy (their sizes are static) and returned as
``jnp`` arrays in the default float dtype (or ``dtype``), so they can be closed over by jitted code.

Rules and the polynomial degree they integrate exactly against ``N(0, I)``:

========================  =========================  ==================================
rule                      points                     exact for total degree
========================  =========================  ==================================
:func:`cubature`          ``2d``                     3 (seed 001 eq 7)
:func:`unscented`         ``2d + 1``                 3 (seed 002 eqs 27–29)
:func:`gauss_hermite`     ``order^d``                ``2 order - 1`` in each coordinate
:func:`smolyak`           see :func:`smolyak`        ``2 level - 1`` (13 points: d=6, level 2)
========================  =========================  ==================================
"""

from __future__ import annotations

import itertools
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import gaussian
from gmjax._types import Array, ArrayLike, DTypeLike

__all__ = [
    "SigmaPoints",
    "cubature",
    "unscented",
    "gauss_hermite",
    "smolyak",
    "transform",
    "expectation",
]


class SigmaPoints(NamedTuple):
    """A quadrature rule for ``N(0, I_d)``.

    Attributes:
        points: ``(n, d)`` nodes ``z_i``.
        wm: ``(n,)`` weights for means (sum to 1; may be negative for UT / Smolyak rules).
        wc: ``(n,)`` weights for covariances (equal to ``wm`` except for the scaled UT, whose
            centre weight carries the extra ``1 - alpha^2 + beta`` of seed 002 eq 27).
    """

    points: Array
    wm: Array
    wc: Array

    @property
    def num_points(self) -> int:
        return self.points.shape[0]

    @property
    def dim(self) -> int:
        return self.points.shape[1]


def _check_dim(d: int) -> int:
    if isinstance(d, bool) or not isinstance(d, (int, np.integer)) or d < 1:
        raise ValueError(f"d: the dimension must be a positive integer, got {d!r}")
    return int(d)


def _as_rule(points: np.ndarray, wm: np.ndarray, wc: np.ndarray, dtype) -> SigmaPoints:
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    return SigmaPoints(jnp.asarray(points, dtype), jnp.asarray(wm, dtype), jnp.asarray(wc, dtype))


def cubature(d: int, *, dtype: DTypeLike | None = None) -> SigmaPoints:
    """Third-degree spherical-radial cubature rule (seed 001 eq 7; Arasaratnam & Haykin 2009).

    Points ``sqrt(d) * [I_d, -I_d]`` (columns), equal weights ``1 / (2d)``.

    Args:
        d: state dimension.
        dtype: floating dtype of the arrays (default: JAX's default float).

    Returns:
        A :class:`SigmaPoints` with ``2d`` points.
    """
    d = _check_dim(d)
    eye = np.eye(d)
    pts = math.sqrt(d) * np.concatenate([eye, -eye], axis=0)
    w = np.full(2 * d, 1.0 / (2 * d))
    return _as_rule(pts, w, w, dtype)


def unscented(
    d: int,
    alpha: float = 1.0,
    beta: float = 0.0,
    kappa: float | None = None,
    *,
    dtype: DTypeLike | None = None,
) -> SigmaPoints:
    """Scaled unscented transform points (seed 002 eqs 27–29; Julier 2002, Wan & van der Merwe 2000).

    With ``lambda = alpha^2 (d + kappa) - d`` (the paper writes ``epsilon`` for ``alpha``):
    ``z_0 = 0``, ``z_l = +/- sqrt(d + lambda) e_l``; ``wm_0 = lambda / (d + lambda)``,
    ``wc_0 = wm_0 + 1 - alpha^2 + beta``, all other weights ``1 / (2 (d + lambda))``.
    The point order (centre, ``+e_1..+e_d``, ``-e_1..-e_d``) is FilterPy's
    ``MerweScaledSigmaPoints`` order.

    Defaults: ``alpha = 1``, ``beta = 0`` and ``kappa = None``, meaning ``kappa = 3 - d``
    (Julier & Uhlmann's choice, which also matches the fourth moment of each coordinate). For
    ``d > 3`` that default gives a negative centre weight; pass ``kappa = 0`` for non-negative
    weights (the paper's recommendation ``kappa >= 0``), or FilterPy's typical
    ``alpha = 1e-3, beta = 2, kappa = 0`` / ``3 - d``.

    Args:
        d: state dimension.
        alpha: spread, ``alpha > 0`` (the paper asks ``0 < alpha <= 1``; larger values are
            allowed).
        beta: prior-knowledge term in ``wc_0`` (2 is optimal for Gaussians).
        kappa: secondary scaling; ``None`` means ``3 - d``.
        dtype: floating dtype of the arrays.

    Returns:
        A :class:`SigmaPoints` with ``2d + 1`` points.

    Raises:
        ValueError: if ``alpha <= 0`` or ``d + lambda <= 0`` (the points would be imaginary)
            or a parameter is not finite.
    """
    d = _check_dim(d)
    if kappa is None:
        kappa = 3.0 - d
    for name, v in (("alpha", alpha), ("beta", beta), ("kappa", kappa)):
        if not np.isfinite(float(v)):
            raise ValueError(f"{name}: must be a finite number, got {v!r}")
    if alpha <= 0:
        raise ValueError(f"alpha: must be > 0, got {alpha!r}")
    lam = alpha**2 * (d + kappa) - d
    c = d + lam
    if c <= 0:
        raise ValueError(
            f"kappa: d + lambda = alpha^2 (d + kappa) = {c:g} must be > 0 (got alpha={alpha}, "
            f"kappa={kappa}, d={d})"
        )
    eye = np.eye(d)
    pts = np.concatenate([np.zeros((1, d)), math.sqrt(c) * eye, -math.sqrt(c) * eye], axis=0)
    wm = np.full(2 * d + 1, 1.0 / (2.0 * c))
    wc = wm.copy()
    wm[0] = lam / c
    wc[0] = lam / c + (1.0 - alpha**2 + beta)
    return _as_rule(pts, wm, wc, dtype)


def _gh_1d(order: int) -> tuple[np.ndarray, np.ndarray]:
    """1-D Gauss–Hermite rule for ``N(0, 1)`` (seed 002 eqs 35–37)."""
    eps, varpi = np.polynomial.hermite.hermgauss(order)  # weight exp(-x^2), eq 35
    z = math.sqrt(2.0) * eps  # eq 36
    w = varpi / math.sqrt(math.pi)
    w = w / w.sum()  # exact to rounding; removes the last ulp
    return z, w


def _check_positive_int(name: str, v) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise ValueError(f"{name}: must be a positive integer, got {v!r}")
    return int(v)


def gauss_hermite(d: int, order: int, *, dtype: DTypeLike | None = None) -> SigmaPoints:
    """Tensor-product Gauss–Hermite rule (seed 002 eqs 35–38).

    The 1-D rule with ``order`` nodes (zeros of the Hermite polynomial, normalised by eq 36) is
    exact for polynomials of degree ``2 order - 1``; the tensor product integrates every monomial
    whose exponent in each coordinate is at most ``2 order - 1``.

    Args:
        d: dimension.
        order: nodes per dimension (``>= 1``).
        dtype: floating dtype.

    Returns:
        A :class:`SigmaPoints` with ``order ** d`` points.
    """
    d = _check_dim(d)
    order = _check_positive_int("order", order)
    if order**d > 10_000_000:
        raise ValueError(f"order: order**d = {order**d} points is too many; use smolyak")
    z, w = _gh_1d(order)
    grids = np.meshgrid(*([z] * d), indexing="ij")
    pts = np.stack([g.reshape(-1) for g in grids], axis=1)
    wgrids = np.meshgrid(*([w] * d), indexing="ij")
    wts = np.prod(np.stack([g.reshape(-1) for g in wgrids], axis=1), axis=1)
    return _as_rule(pts, wts, wts, dtype)


_GROWTHS = ("linear", "exponential")


def _nodes_at_level(level: int, growth: str) -> int:
    if growth == "linear":
        return 2 * level - 1
    return 2**level - 1


def smolyak(d: int, level: int, growth: str = "linear", *, dtype: DTypeLike | None = None) -> SigmaPoints:
    """Smolyak sparse-grid Gauss–Hermite rule (seed 002 §II-C, refs [31]–[33]).

    Smolyak's combination of 1-D Gauss–Hermite rules ``Q_l`` (level ``l >= 1``):

    .. math:: A(L, d) = \\sum_{L \\le |i| \\le L + d - 1} (-1)^{L + d - 1 - |i|}
              \\binom{d - 1}{|i| - L}\\, Q_{i_1} \\otimes \\cdots \\otimes Q_{i_d},

    with ``|i| = i_1 + ... + i_d`` and every ``i_j >= 1``. Coinciding nodes (all odd 1-D rules
    share the origin) are merged by summing their weights; negative weights are kept. The rule
    is exact for every polynomial of total degree ``<= 2 L - 1``.

    ``growth`` sets the number of 1-D nodes at level ``l``: ``"linear"`` → ``2l - 1`` (Jia, Xin &
    Cheng's sparse-grid quadrature filter), ``"exponential"`` → ``2^l - 1``. Both give the
    paper's 13-point rule at level 2 in 6-D (seed 002 §V: "accuracy level of two … 13 quadrature
    points"), i.e. ``2d + 1`` points at level 2.

    Args:
        d: dimension.
        level: accuracy level ``L >= 1``.
        growth: ``"linear"`` or ``"exponential"``.
        dtype: floating dtype.

    Returns:
        A :class:`SigmaPoints` (merged nodes, lexicographic order).

    Raises:
        ValueError: unknown ``growth``, non-positive ``level`` or ``d``.
    """
    d = _check_dim(d)
    level = _check_positive_int("level", level)
    if growth not in _GROWTHS:
        raise ValueError(f"growth: must be one of {_GROWTHS}, got {growth!r}")
    rules = {l: _gh_1d(_nodes_at_level(l, growth)) for l in range(1, level + 1)}
    acc: dict[tuple, float] = {}
    coords: dict[tuple, np.ndarray] = {}
    lo = max(d, level)
    hi = level + d - 1
    for multi in itertools.product(range(1, level + 1), repeat=d):
        s = sum(multi)
        if s < lo or s > hi:
            continue
        coef = (-1) ** (hi - s) * math.comb(d - 1, s - level)
        if coef == 0:
            continue
        for combo in itertools.product(*(range(len(rules[l][0])) for l in multi)):
            pt = np.array([rules[l][0][j] for l, j in zip(multi, combo)])
            wt = coef * float(np.prod([rules[l][1][j] for l, j in zip(multi, combo)]))
            key = tuple(np.round(pt, 12) + 0.0)  # + 0.0 turns -0.0 into 0.0
            acc[key] = acc.get(key, 0.0) + wt
            coords.setdefault(key, pt)
    keys = sorted(k for k in acc if abs(acc[k]) > 1e-14)
    pts = np.stack([coords[k] for k in keys])
    wts = np.array([acc[k] for k in keys])
    return _as_rule(pts, wts, wts, dtype)


def transform(rule: SigmaPoints, mean: ArrayLike, cov_or_chol: ArrayLike, *, is_chol: bool = False) -> Array:
    """Map a rule for ``N(0, I)`` to ``N(mean, P)``: ``x_i = mean + L z_i`` (seed 002 eq 38).

    Args:
        rule: a :class:`SigmaPoints` of dimension ``d``.
        mean: ``(d,)``.
        cov_or_chol: ``(d, d)`` covariance ``P`` (factored with :func:`gaussian.safe_cholesky`,
            so a slightly indefinite ``P`` is repaired) or, with ``is_chol=True``, any square root
            ``L`` with ``L L^T = P``.
        is_chol: whether ``cov_or_chol`` is already a square-root factor.

    Returns:
        ``(n, d)`` points.
    """
    mean = jnp.asarray(mean)
    m = jnp.asarray(cov_or_chol)
    L = m if is_chol else gaussian.safe_cholesky(m).factor
    return mean + rule.points.astype(L.dtype) @ L.T


def expectation(
    rule: SigmaPoints,
    fn: Callable[[Array], Array],
    mean: ArrayLike,
    cov_or_chol: ArrayLike,
    *,
    is_chol: bool = False,
) -> Array:
    """``E[fn(x)]`` for ``x ~ N(mean, P)`` by the rule: ``sum_i wm_i fn(mean + L z_i)`` (eq 38).

    ``fn`` maps ``(d,)`` to any array; it is ``vmap``-ed over the points.
    """
    pts = transform(rule, mean, cov_or_chol, is_chol=is_chol)
    vals = jax.vmap(fn)(pts)
    return jnp.tensordot(rule.wm.astype(vals.dtype), vals, axes=1)
