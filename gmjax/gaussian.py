"""Single-Gaussian algebra, the one numerical layer: safe Cholesky, log-density, product normaliser,
Mahalanobis, KL, and the two-component moment merge.

Two families, both dtype-generic and jit/vmap/grad-safe:

* functions of one Gaussian (mean ``(d,)``, covariance ``(d, d)``; batch with ``jax.vmap``) that go
  through :func:`safe_cholesky` (a non-PD input is repaired, and the repair is reported);
* ``spd_*`` kernels that broadcast over leading axes and assume SPD inputs (no repair): closed forms for
  ``d = 1`` and ``d = 2`` (the static reduction benchmark and the PCRB coarsening are 1-D and 2-D and
  evaluate them ``K^2`` times per step), a Cholesky factor above. The reducers' cost matrices use them.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve, solve_triangular

from gmjax._types import Array, ArrayLike, Matrix, Scalar

__all__ = [
    "CholeskyResult",
    "symmetrize",
    "small_matmul",
    "safe_cholesky",
    "repair_spd",
    "solve_lower",
    "cho_solve_small",
    "logdet",
    "logpdf",
    "pdf",
    "log_product_normalizer",
    "product_normalizer",
    "mahalanobis_sq",
    "mahalanobis",
    "kl_divergence",
    "inv_spd",
    "spd_logdet",
    "spd_inv",
    "spd_inv_quad",
    "spd_logpdf",
    "spd_kl",
    "spd_kl_from_inverse",
    "moment_merge_pair",
]

_LOG_2PI = 1.8378770664093453  # log(2 pi), the one definition (mixture and the filters read it)


class CholeskyResult(NamedTuple):
    """Lower Cholesky factor and whether the input had to be repaired.

    Attributes:
        factor: ``(d, d)`` lower-triangular ``L`` with ``L @ L.T`` = the (repaired) covariance.
        repaired: ``()`` bool, True when the symmetrised input was not numerically positive
            definite and jitter was added on the diagonal.
        jitter: ``()`` the jitter that was added (0 when not repaired).
    """

    factor: Matrix
    repaired: Array
    jitter: Scalar


def symmetrize(a: ArrayLike) -> Array:
    """Return ``(a + a^T) / 2`` over the last two axes."""
    a = jnp.asarray(a)
    return 0.5 * (a + jnp.swapaxes(a, -1, -2))


_UNROLL_MAX_DIM = 6


def _unrolled_elimination(a: Array, bad_pivot: float) -> tuple[list[list[Array]], list[Array]]:
    """The Cholesky elimination of ``(..., d, d)`` ``a`` unrolled at trace time (``d <= 6``).

    Returns the factor's entries ``cols[i][j]`` (``j <= i``; ``None`` above the diagonal) and the
    pivots; a non-positive pivot's square root is taken of ``bad_pivot`` instead.
    """
    d = a.shape[-1]
    cols: list[list[Array]] = [[None] * d for _ in range(d)]  # type: ignore[list-item]
    pivots: list[Array] = []
    zero = jnp.zeros_like(a[..., 0, 0])
    for j in range(d):
        diag = a[..., j, j] - sum((cols[j][k] ** 2 for k in range(j)), zero)
        pivots.append(diag)
        ljj = jnp.sqrt(jnp.where(diag > 0, diag, bad_pivot))
        cols[j][j] = ljj
        for i in range(j + 1, d):
            off = a[..., i, j] - sum((cols[i][k] * cols[j][k] for k in range(j)), zero)
            cols[i][j] = off / ljj
    return cols, pivots


def _unrolled_ldl_pivots(a: Array) -> list[Array]:
    """The pivots ``D_j`` of the ``L D L^T`` elimination of ``(..., d, d)`` ``a`` (unit lower ``L``),
    unrolled at trace time (``d <= 6``): ``D_j = a_jj - sum_k L_jk^2 D_k``. The same numbers as the
    squared Cholesky diagonal ``L_jj^2`` (to rounding) with no square root; ``prod_j D_j = det a``.
    A non-positive pivot is returned as it is (the caller decides)."""
    d = a.shape[-1]
    unit: list[list[Array]] = [[None] * d for _ in range(d)]  # type: ignore[list-item]
    pivots: list[Array] = []
    for j in range(d):
        dj = a[..., j, j]
        for k in range(j):
            dj = dj - unit[j][k] * unit[j][k] * pivots[k]
        pivots.append(dj)
        for i in range(j + 1, d):
            v = a[..., i, j]
            for k in range(j):
                v = v - unit[i][k] * unit[j][k] * pivots[k]
            unit[i][j] = v / dj
    return pivots


def _cholesky(a: Array) -> Array:
    """Lower Cholesky factor; NaN where ``a`` is not positive definite.

    For ``d <= 6`` the factorisation is unrolled at trace time into elementwise operations, which
    XLA vectorises across ``vmap`` batches far better than a batched LAPACK call on tiny matrices.
    """
    d = a.shape[-1]
    if d > _UNROLL_MAX_DIM:
        return jnp.linalg.cholesky(a)
    # sqrt of a non-positive pivot is NaN (caught by the caller), as LAPACK's failure is.
    cols, _ = _unrolled_elimination(a, jnp.nan)
    zero = jnp.zeros_like(a[..., 0, 0])
    rows = [jnp.stack([cols[i][j] if j <= i else zero for j in range(d)], -1) for i in range(d)]
    return jnp.stack(rows, -2)


def _is_positive_definite(a: Array) -> Array:
    """``()`` bool: the Cholesky factorisation of symmetric ``a`` succeeds (every pivot positive and
    finite). For ``d <= 6`` only the pivots of the unrolled elimination are used (no factor)."""
    if a.shape[-1] > _UNROLL_MAX_DIM:
        return jnp.all(jnp.isfinite(jnp.linalg.cholesky(a)))
    _, pivots = _unrolled_elimination(a, 1.0)
    # a non-finite entry makes some pivot NaN or -inf
    return functools.reduce(jnp.logical_and, [(p > 0) & jnp.isfinite(p) for p in pivots])


def solve_lower(L: ArrayLike, b: ArrayLike) -> Array:
    """Solve ``L x = b`` for lower-triangular ``L`` ``(d, d)`` and ``b`` ``(d,)`` or ``(d, n)``."""
    L = jnp.asarray(L)
    b = jnp.asarray(b)
    d = L.shape[-1]
    if d > _UNROLL_MAX_DIM:
        return solve_triangular(L, b, lower=True)
    xs: list[Array] = []
    for i in range(d):
        acc = b[i]
        for k in range(i):
            acc = acc - L[i, k] * xs[k]
        xs.append(acc / L[i, i])
    return jnp.stack(xs, 0)


def _solve_lower_transposed(L: Array, b: Array) -> Array:
    """Solve ``L^T x = b`` (back substitution, unrolled; ``d <= 6``)."""
    d = L.shape[-1]
    xs: list[Array] = [None] * d  # type: ignore[list-item]
    for i in reversed(range(d)):
        acc = b[i]
        for k in range(i + 1, d):
            acc = acc - L[k, i] * xs[k]
        xs[i] = acc / L[i, i]
    return jnp.stack(xs, 0)


def cho_solve_small(L: ArrayLike, b: ArrayLike) -> Array:
    """Solve ``(L L^T) x = b`` for a lower Cholesky factor ``L`` ``(d, d)`` and ``b`` ``(d,)`` or ``(d, n)``.

    ``jax.scipy.linalg.cho_solve``'s values; for ``d <= 6`` both triangular solves are unrolled into
    elementwise operations (on CPU a batched ``cho_solve`` calls LAPACK once per tiny matrix).
    """
    L = jnp.asarray(L)
    b = jnp.asarray(b)
    if L.shape[-1] > _UNROLL_MAX_DIM:
        return cho_solve((L, True), b)
    return _solve_lower_transposed(L, solve_lower(L, b))


def _gershgorin_shift(s: Array) -> Array:
    """A diagonal shift that makes ``s`` diagonally dominant (so PD): ``max_i(sum_j!=i |s_ij| - s_ii)``."""
    off = jnp.sum(jnp.abs(s), axis=-1) - jnp.abs(jnp.diagonal(s))
    return jnp.maximum(jnp.max(off - jnp.diagonal(s)), 0.0)


def safe_cholesky(cov: ArrayLike) -> CholeskyResult:
    """Cholesky factor of a covariance that may have drifted off positive definiteness.

    The input is symmetrised. If its Cholesky factor is not finite, the jitter
    ``2 max(-g, 0) + sqrt(eps) mean|diag|`` is added to the diagonal, where ``g`` is the Gershgorin
    lower bound of the smallest eigenvalue, so the jittered matrix is provably positive definite;
    the result is flagged. (The bound can exceed the true deficit, so a repaired covariance may be
    inflated more than strictly needed; that is the price of needing no eigen-decomposition, which
    would cost seconds of compile time at every call site on CPU.) The jitter is computed under
    ``stop_gradient`` and the failing factorisation is never differentiated, so values and
    gradients stay finite.

    Args:
        cov: ``(d, d)`` covariance.

    Returns:
        A :class:`CholeskyResult`.
    """
    sym = symmetrize(cov)
    d = sym.shape[-1]
    repaired, jitter = _repair_jitter(sym)
    factor = _cholesky(sym + jitter * jnp.eye(d, dtype=sym.dtype))
    return CholeskyResult(factor, repaired, jitter)


def _repair_jitter(sym: Array) -> tuple[Array, Array]:
    """``(repaired, jitter)`` of :func:`safe_cholesky` for a symmetric ``sym`` (stopped gradients).

    For ``d <= 6`` the Gershgorin shift and the scale are unrolled over the entries: XLA's CPU
    reductions over a trailing ``(d, d)`` pair cost more than the arithmetic.
    """
    const = jax.lax.stop_gradient(sym)
    repaired = ~_is_positive_definite(const)
    d = const.shape[-1]
    if d > _UNROLL_MAX_DIM:
        scale = jnp.mean(jnp.abs(jnp.diagonal(const)))
        gershgorin = _gershgorin_shift(const)
    else:
        absolute = [[jnp.abs(const[..., i, j]) for j in range(d)] for i in range(d)]
        scale = functools.reduce(jnp.add, [absolute[i][i] for i in range(d)]) / d
        rows = [sum(absolute[i][j] for j in range(d) if j != i) - const[..., i, i] for i in range(d)]
        gershgorin = functools.reduce(jnp.maximum, rows, jnp.zeros_like(const[..., 0, 0]))
    scale = jnp.where(scale > 0, scale, 1.0)  # an all-zero covariance has no scale of its own
    shift = 2.0 * gershgorin + jnp.sqrt(jnp.finfo(sym.dtype).eps) * scale
    return repaired, jnp.where(repaired, shift, jnp.zeros((), sym.dtype))


def repair_spd(cov: ArrayLike) -> tuple[Matrix, Array]:
    """Symmetrise ``cov``; if it is not numerically positive definite, add :func:`safe_cholesky`'s
    jitter to its diagonal (the matrix that function factorises). One Cholesky factorisation.

    Returns:
        ``(cov, repaired)``.
    """
    sym = symmetrize(cov)
    repaired, jitter = _repair_jitter(sym)
    return sym + jitter * jnp.eye(sym.shape[-1], dtype=sym.dtype), repaired


def _chol(cov: ArrayLike) -> Matrix:
    return safe_cholesky(cov).factor


def logdet(cov: ArrayLike) -> Scalar:
    """``log det(cov)`` through a (safe) Cholesky factor."""
    L = _chol(cov)
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(L)))


def inv_spd(cov: ArrayLike) -> Matrix:
    """Inverse of a symmetric positive definite matrix through its Cholesky factor."""
    L = _chol(cov)
    eye = jnp.eye(L.shape[-1], dtype=L.dtype)
    return symmetrize(cho_solve_small(L, eye))


def _check_dims(**arrays: ArrayLike) -> None:
    """Static check that points ``(..., d)`` and covariances ``(..., d, d)`` share ``d``.

    Names ending in ``cov`` are covariances. Raises ``ValueError`` naming the arguments.
    """
    dims = {}
    for name, a in arrays.items():
        shape = jnp.shape(a)
        if name.startswith("cov"):
            if len(shape) < 2 or shape[-1] != shape[-2]:
                raise ValueError(f"{name}: expected a square (d, d) matrix, got shape {shape}")
        elif len(shape) < 1:
            raise ValueError(f"{name}: expected a (d,) vector, got a scalar")
        dims[name] = shape[-1]
    if len(set(dims.values())) > 1:
        raise ValueError("dimension mismatch: " + ", ".join(f"{n} has d={v}" for n, v in dims.items()))


def mahalanobis_sq(x: ArrayLike, mean: ArrayLike, cov: ArrayLike) -> Scalar:
    """Squared Mahalanobis distance ``(x - m)^T P^{-1} (x - m)``.

    Args:
        x: ``(d,)`` point. mean: ``(d,)``. cov: ``(d, d)``.
    """
    _check_dims(x=x, mean=mean, cov=cov)
    L = _chol(cov)
    r = solve_lower(L, jnp.asarray(x) - jnp.asarray(mean))
    return jnp.sum(r * r)


def mahalanobis(x: ArrayLike, mean: ArrayLike, cov: ArrayLike) -> Scalar:
    """Mahalanobis distance ``sqrt((x - m)^T P^{-1} (x - m))`` (gradient-safe at 0)."""
    sq = mahalanobis_sq(x, mean, cov)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def logpdf(x: ArrayLike, mean: ArrayLike, cov: ArrayLike) -> Scalar:
    """Log-density of ``N(x; mean, cov)``.

    Args:
        x: ``(d,)`` point. mean: ``(d,)``. cov: ``(d, d)``.
    """
    _check_dims(x=x, mean=mean, cov=cov)
    L = _chol(cov)
    d = L.shape[-1]
    r = solve_lower(L, jnp.asarray(x) - jnp.asarray(mean))
    return -0.5 * (d * _LOG_2PI + jnp.sum(r * r)) - jnp.sum(jnp.log(jnp.diagonal(L)))


def pdf(x: ArrayLike, mean: ArrayLike, cov: ArrayLike) -> Scalar:
    """Density of ``N(x; mean, cov)``."""
    return jnp.exp(logpdf(x, mean, cov))


def log_product_normalizer(mean1: ArrayLike, cov1: ArrayLike, mean2: ArrayLike, cov2: ArrayLike) -> Scalar:
    """``log ∫ N(x; m1, P1) N(x; m2, P2) dx = log N(m1; m2, P1 + P2)`` (seed 000 eqs 34–35).

    ``P1 + P2`` is positive definite whenever both inputs are, so no jitter repair is attempted:
    this is the inner kernel of every ISE and runs ``K·L`` times per mixture pair.
    """
    _check_dims(mean1=mean1, cov1=cov1, mean2=mean2, cov2=cov2)
    S = symmetrize(jnp.asarray(cov1) + jnp.asarray(cov2))
    L = _cholesky(S)
    d = L.shape[-1]
    r = solve_lower(L, jnp.asarray(mean1) - jnp.asarray(mean2))
    return -0.5 * (d * _LOG_2PI + jnp.sum(r * r)) - jnp.sum(jnp.log(jnp.diagonal(L)))


def product_normalizer(mean1: ArrayLike, cov1: ArrayLike, mean2: ArrayLike, cov2: ArrayLike) -> Scalar:
    """``∫ N(x; m1, P1) N(x; m2, P2) dx = N(m1; m2, P1 + P2)`` (seed 000 eqs 34–35)."""
    return jnp.exp(log_product_normalizer(mean1, cov1, mean2, cov2))


def kl_divergence(mean1: ArrayLike, cov1: ArrayLike, mean2: ArrayLike, cov2: ArrayLike) -> Scalar:
    """``KL(N(m1, P1) || N(m2, P2))`` in closed form.

    ``0.5 * [tr(P2^{-1} P1) + (m2 - m1)^T P2^{-1} (m2 - m1) - d + log det P2 - log det P1]``.
    """
    _check_dims(mean1=mean1, cov1=cov1, mean2=mean2, cov2=cov2)
    L1 = _chol(cov1)
    L2 = _chol(cov2)
    d = L1.shape[-1]
    a = solve_lower(L2, L1)  # L2^{-1} L1
    trace = jnp.sum(a * a)
    r = solve_lower(L2, jnp.asarray(mean2) - jnp.asarray(mean1))
    logdet_ratio = 2.0 * (jnp.sum(jnp.log(jnp.diagonal(L2))) - jnp.sum(jnp.log(jnp.diagonal(L1))))
    return 0.5 * (trace + jnp.sum(r * r) - d + logdet_ratio)


# ----------------------------------------------------------------------------- broadcasting SPD kernels


def small_matmul(a: Array, b: Array) -> Array:
    """``a @ b`` for ``(..., d, d)`` matrices, unrolled over ``d <= 6`` into elementwise products
    summed left to right (a plain ``@`` above).

    XLA's CPU ``dot_general`` on batches of tiny matrices calls a kernel per matrix, and hands large
    batches to kernels that sum in another order; the unrolled form is faster there and gives every
    batch element the same bits whatever the batch (what :func:`spd_inv`'s ``fixed_order`` is for).
    """
    if a.shape[-1] > _UNROLL_MAX_DIM:
        return a @ b
    return functools.reduce(jnp.add, [a[..., :, k, None] * b[..., None, k, :] for k in range(a.shape[-1])])


def spd_logdet(P: jax.Array, *, fixed_order: bool = False) -> jax.Array:
    """``log det P`` for ``(..., d, d)`` SPD matrices (closed form for d <= 2); NaN where ``P`` is
    not positive definite.

    For ``3 <= d <= 6``: ``sum_j log D_j`` over the pivots of the unrolled ``L D L^T`` elimination,
    summed left to right, elementwise (no square roots, no factor built: 2-3x faster under ``vmap``
    than the logs of a Cholesky diagonal, the same value to rounding), so the result never depends on
    the batch it is computed in; ``fixed_order`` (static) is kept for :func:`spd_inv`'s signature and
    changes nothing here. Above ``d = 6``: LAPACK's Cholesky.
    """
    del fixed_order  # every d <= 6 path is elementwise in a fixed order
    d = P.shape[-1]
    if d == 1:
        return jnp.log(P[..., 0, 0])
    if d == 2:
        return jnp.log(P[..., 0, 0] * P[..., 1, 1] - P[..., 0, 1] * P[..., 1, 0])
    if d <= _UNROLL_MAX_DIM:
        logs = [jnp.log(jnp.where(p > 0, p, jnp.nan)) for p in _unrolled_ldl_pivots(P)]
        return functools.reduce(jnp.add, logs)
    L = jnp.linalg.cholesky(P)
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), axis=-1)


def spd_inv(P: jax.Array, *, fixed_order: bool = False) -> jax.Array:
    """Inverse of ``(..., d, d)`` SPD matrices (closed form for d <= 2), symmetrised.

    ``fixed_order`` (static): for ``3 <= d <= 6`` form ``L^{-T} L^{-1}`` by :func:`small_matmul`
    (batch-independent bits) instead of a batched matrix product.
    """
    d = P.shape[-1]
    if d == 1:
        return 1.0 / P
    if d == 2:
        a, b, c, e = P[..., 0, 0], P[..., 0, 1], P[..., 1, 0], P[..., 1, 1]
        det = a * e - b * c
        out = jnp.stack([jnp.stack([e, -b], -1), jnp.stack([-c, a], -1)], -2) / det[..., None, None]
        return 0.5 * (out + jnp.swapaxes(out, -1, -2))
    if d > _UNROLL_MAX_DIM:
        L = jnp.linalg.cholesky(P)
        eye = jnp.broadcast_to(jnp.eye(d, dtype=P.dtype), P.shape)
        Linv = jax.scipy.linalg.solve_triangular(L, eye, lower=True)
    else:
        Linv = _lower_inverse(_cholesky(P))
        if fixed_order:
            return small_matmul(jnp.swapaxes(Linv, -1, -2), Linv)
    return jnp.swapaxes(Linv, -1, -2) @ Linv


def spd_inv_quad(x: jax.Array, P: jax.Array) -> jax.Array:
    """``x^T P^{-1} x`` for ``x`` ``(..., d)`` and SPD ``P`` ``(..., d, d)``."""
    d = P.shape[-1]
    if d == 1:
        return x[..., 0] ** 2 / P[..., 0, 0]
    if d == 2:
        a, b, e = P[..., 0, 0], P[..., 0, 1], P[..., 1, 1]
        det = a * e - b * b
        x0, x1 = x[..., 0], x[..., 1]
        return (e * x0 * x0 - 2.0 * b * x0 * x1 + a * x1 * x1) / det
    if d > _UNROLL_MAX_DIM:
        L = jnp.linalg.cholesky(P)
        r = jax.scipy.linalg.solve_triangular(L, x[..., None], lower=True)[..., 0]
        return jnp.sum(r * r, axis=-1)
    L = _cholesky(P)
    x = jnp.broadcast_to(x, jnp.broadcast_shapes(x.shape, L.shape[:-1]))
    rs: list[Array] = []
    for i in range(d):  # forward substitution, broadcast over the leading axes
        acc = x[..., i]
        for k in range(i):
            acc = acc - L[..., i, k] * rs[k]
        rs.append(acc / L[..., i, i])
    return functools.reduce(jnp.add, [r * r for r in rs])


def _lower_inverse(L: Array) -> Array:
    """``L^{-1}`` of lower-triangular ``(..., d, d)`` factors, unrolled (``d <= 6``)."""
    d = L.shape[-1]
    zero = jnp.zeros_like(L[..., 0, 0])
    inv: list[list[Array]] = [[zero] * d for _ in range(d)]
    for i in range(d):
        inv[i][i] = 1.0 / L[..., i, i]
        for j in range(i):
            acc = functools.reduce(jnp.add, [L[..., i, k] * inv[k][j] for k in range(j, i)])
            inv[i][j] = -acc * inv[i][i]
    return jnp.stack([jnp.stack(row, -1) for row in inv], -2)


def spd_logpdf(x: jax.Array, m: jax.Array, P: jax.Array, *, fixed_order: bool = False) -> jax.Array:
    """``log N(x; m, P)`` broadcast over leading axes (``fixed_order``: see :func:`spd_logdet`)."""
    d = P.shape[-1]
    return -0.5 * (d * _LOG_2PI + spd_logdet(P, fixed_order=fixed_order) + spd_inv_quad(x - m, P))


def _sum_entries(entries: list[Array]) -> Array:
    """Entries ``a, b`` of a ``(..., d, d)`` product listed in row-major order, summed left to right
    (``d <= 6``): elementwise, vectorised over the leading axes, in one fixed order whatever the
    batch. Under ``vmap`` a ``reduce`` over the two minor axes of a batch of 4 x 4 matrices is a
    loop per matrix, and a product formed whole and then sliced is read with strides: West's KL row
    at ``d = 4`` took 2.6x as long (the same sum to rounding; XLA's ``reduce`` pairs the terms in
    an order of its own)."""
    return functools.reduce(jnp.add, entries)


def _frobenius(A: Array, B: Array) -> Array:
    """``Σ_ab A_ab B_ab = tr(A^T B)`` of ``(..., d, d)`` matrices (broadcast)."""
    d = A.shape[-1]
    if d > _UNROLL_MAX_DIM:
        return jnp.sum(A * B, axis=(-1, -2))
    return _sum_entries([A[..., a, b] * B[..., a, b] for a in range(d) for b in range(d)])


def _quadratic_form(x: Array, A: Array) -> Array:
    """``x^T A x = Σ_ab x_a A_ab x_b`` for ``x`` ``(..., d)``, ``A`` ``(..., d, d)`` (broadcast)."""
    d = A.shape[-1]
    if d > _UNROLL_MAX_DIM:
        return jnp.sum(x[..., :, None] * A * x[..., None, :], axis=(-1, -2))
    return _sum_entries([x[..., a] * A[..., a, b] * x[..., b] for a in range(d) for b in range(d)])


def spd_kl(m1: Array, P1: Array, m2: Array, P2: Array) -> jax.Array:
    """``KL(N(m1, P1) || N(m2, P2))`` broadcast over leading axes."""
    d = P1.shape[-1]
    P2i = spd_inv(P2)
    tr = _frobenius(P2i, P1)
    return 0.5 * (tr + spd_inv_quad(m2 - m1, P2) - d + spd_logdet(P2) - spd_logdet(P1))


def spd_kl_from_inverse(m1: Array, P1: Array, ld1: Array, m2: Array, P2inv: Array, ld2: Array) -> Array:
    """``KL(N(m1, P1) || N(m2, P2))`` from ``P2^{-1}`` and both log-determinants (``ld1 = log det
    P1``, ``ld2 = log det P2``), broadcast over leading axes: :func:`spd_kl` when the inverses and
    log-determinants are carried (a greedy reduction or a k-means assignment that reuses them).
    ``0.5 [tr(P2^{-1} P1) + (m2 - m1)^T P2^{-1} (m2 - m1) - d + ld2 - ld1]``."""
    d = P1.shape[-1]
    diff = m2 - m1
    tr = _frobenius(P2inv, P1)
    quad = _quadratic_form(diff, P2inv)
    return 0.5 * (tr + quad - d + ld2 - ld1)


def moment_merge_pair(
    w1: Array, m1: Array, P1: Array, w2: Array, m2: Array, P2: Array, *, symmetrize: bool = True
) -> tuple[Array, Array, Array]:
    """Moment-preserving merge of two components (seed 002 eqs 70–72 written with ``lambda_i``).

    ``W = w1 + w2``, ``l_i = w_i / W``, ``m = l1 m1 + l2 m2``,
    ``P = l1 P1 + l2 P2 + l1 l2 (m1 - m2)(m1 - m2)^T``. A pair of zero weights gives equal ``l_i``.
    Broadcasts over leading axes: weights ``(...)``, means ``(..., d)``, covariances ``(..., d, d)``.

    ``symmetrize`` (static): return ``(P + P^T) / 2``. For exactly symmetric ``P1``, ``P2`` the
    formula is already exactly symmetric (every entry and its mirror are the same products), so
    ``False`` changes no bit there; it saves a transposed copy of a batch of merged covariances
    that only feed a Cholesky, which reads the lower triangle (e.g. a row of merge costs).
    """
    W = w1 + w2
    ok = W > 0
    Ws = jnp.where(ok, W, 1.0)
    l1 = jnp.where(ok, w1 / Ws, 0.5)
    l2 = jnp.where(ok, w2 / Ws, 0.5)
    diff = m1 - m2
    m = l1[..., None] * m1 + l2[..., None] * m2
    P = (
        l1[..., None, None] * P1
        + l2[..., None, None] * P2
        + (l1 * l2)[..., None, None] * diff[..., :, None] * diff[..., None, :]
    )
    return W, m, 0.5 * (P + jnp.swapaxes(P, -1, -2)) if symmetrize else P
