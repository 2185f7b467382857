"""The cardinality distribution's algebra for the GM-CPHD filter (Vo, Vo & Cantoni 2007), in the log
domain with fixed shapes: Poisson pmfs, elementary symmetric functions (Vieta's recursion), the
cardinality prediction (binomial thinning convolved with the births) and the ``Upsilon`` terms of the
update. See :mod:`gmjax.multitarget.cphd` for the recursion they serve.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.special import gammaln

from gmjax._types import Array, ArrayLike

__all__ = [
    "poisson_log_pmf",
    "cardinality_moments",
    "log_esf",
    "log_esf_leave_one_out",
    "predict_cardinality",
    "log_upsilon",
]


# ----------------------------------------------------------------------------- log-domain helpers


def _lse(x: Array, axis: int = -1) -> Array:
    """``logsumexp`` along ``axis``, ``-inf`` for an all ``-inf`` slice, with finite gradients."""
    mx = jnp.max(x, axis=axis, keepdims=True)
    finite = jnp.isfinite(mx)
    mx = jax.lax.stop_gradient(jnp.where(finite, mx, 0.0))
    s = jnp.sum(jnp.exp(x - mx), axis=axis, keepdims=True)
    out = jnp.where(finite, mx + jnp.log(jnp.where(finite, s, 1.0)), -jnp.inf)
    return jnp.squeeze(out, axis)


def _logaddexp(a: Array, b: Array) -> Array:
    return _lse(jnp.stack([a, b]), axis=0)


def _xlog(k: Array, x: Array) -> Array:
    """``k log x`` with ``0^0 = 1`` (``0`` where ``k == 0``) and ``-inf`` for ``x = 0 < k``."""
    pos = x > 0
    lx = jnp.log(jnp.where(pos, x, 1.0))
    return jnp.where(k == 0, 0.0, jnp.where(pos, k * lx, -jnp.inf))


def poisson_log_pmf(n_max: int, mean: ArrayLike) -> Array:
    """``(n_max + 1,)`` ``log Poisson(n; mean)``, ``n = 0 .. n_max`` (``mean = 0``: a point mass at 0)."""
    mean = jnp.asarray(mean)
    n = jnp.arange(n_max + 1)
    return -mean + _xlog(n, mean) - gammaln(n + 1.0).astype(mean.dtype)


def _normalize_log(log_p: Array) -> tuple[Array, Array]:
    """``(log p - log sum p, log sum p)``; unchanged where the sum is 0."""
    total = _lse(log_p)
    ok = jnp.isfinite(total)
    return jnp.where(ok, log_p - jnp.where(ok, total, 0.0), log_p), total


def cardinality_moments(log_cardinality: Array) -> tuple[Array, Array]:
    """``(mean, variance)`` of the cardinality distribution ``(N_max + 1,)``."""
    p = jnp.exp(log_cardinality)
    n = jnp.arange(p.shape[-1], dtype=p.dtype)
    mean = jnp.sum(n * p, axis=-1)
    var = jnp.sum(jnp.square(n - mean[..., None]) * p, axis=-1)
    return mean, var


# ----------------------------------------------------------------------------- elementary symmetric functions


def log_esf(log_x: Array, mask: Array | None = None) -> Array:
    """``log e_j(X)``, ``j = 0 .. M``, of the values ``X = {x_i : mask_i}`` given as ``log x_i``.

    Vieta's recursion ``e_j <- e_j + x_i e_{j-1}`` over the ``M`` slots (the coefficients of
    ``prod_i (1 + x_i t)``), run in the log domain so that ``M`` in the hundreds neither overflows nor
    underflows. A masked slot is the factor ``1`` (skipped); ``log x_i = -inf`` is ``x_i = 0``.

    Args:
        log_x: ``(M,)`` ``log x_i``.
        mask: ``(M,)`` bool, which slots hold a value (default: all).

    Returns:
        ``(M + 1,)`` ``log e_j``; ``-inf`` for ``j`` above the number of non-zero values.
    """
    log_x = jnp.asarray(log_x)
    M = log_x.shape[-1]
    mask = jnp.ones(M, bool) if mask is None else jnp.asarray(mask, bool)
    dtype = log_x.dtype
    init = jnp.concatenate([jnp.zeros(1, dtype), jnp.full(M, -jnp.inf, dtype)])
    neg = jnp.full(1, -jnp.inf, dtype)

    def step(le, inputs):
        lx, valid = inputs
        new = _logaddexp(le, lx + jnp.concatenate([neg, le[:-1]]))
        return jnp.where(valid, new, le), None

    le, _ = jax.lax.scan(step, init, (jnp.where(mask, log_x, -jnp.inf), mask))
    return le


def log_esf_leave_one_out(log_x: Array, mask: Array | None = None) -> Array:
    """``(M, M + 1)``: row ``i`` is :func:`log_esf` of ``X`` without slot ``i`` (``e_j(Z \\ {z_i})``)."""
    log_x = jnp.asarray(log_x)
    M = log_x.shape[-1]
    mask = jnp.ones(M, bool) if mask is None else jnp.asarray(mask, bool)
    others = mask[None, :] & ~jnp.eye(M, dtype=bool)
    return jax.vmap(lambda mk: log_esf(log_x, mk))(others)


# ----------------------------------------------------------------------------- the cardinality recursion


def predict_cardinality(log_p: Array, survival_prob: ArrayLike, birth_mean: ArrayLike) -> tuple[Array, Array]:
    """The CPHD cardinality prediction with constant ``P_S`` and a Poisson birth cardinality.

    ``p_{k|k-1}(n) = sum_{j<=n} p_Gamma(n - j) Pi(j)`` with the survivors' binomial thinning
    ``Pi(j) = sum_{l=j}^{N} C(l, j) P_S^j (1 - P_S)^{l - j} p(l)`` (both as fixed ``(N+1, N+1)``
    log-domain matrices, binomial coefficients by ``gammaln``), ``p_Gamma = Poisson(birth_mean)``;
    truncated at ``N = N_max`` and renormalised.

    Args:
        log_p: ``(N + 1,)`` ``log p_{k-1}(n)``.
        survival_prob: ``()`` ``P_S``.
        birth_mean: ``()`` the expected number of births, ``sum`` of the birth weights.

    Returns:
        ``(log p_{k|k-1} (N + 1,), tail)`` with ``tail`` the mass beyond ``N`` that was cut.
    """
    log_p = jnp.asarray(log_p)
    dtype = log_p.dtype
    N1 = log_p.shape[-1]
    p_s = jnp.asarray(survival_prob, dtype)
    n = jnp.arange(N1)
    ell, j = n[:, None], n[None, :]
    below = j <= ell
    k = jnp.where(below, ell - j, 0)
    log_binom = (gammaln(ell + 1.0) - gammaln(j + 1.0) - gammaln(k + 1.0)).astype(dtype)
    log_thin = jnp.where(below, log_binom + _xlog(j, p_s) + _xlog(k, 1.0 - p_s), -jnp.inf)  # (l, j)
    log_pi = _lse(log_p[:, None] + log_thin, axis=0)  # (j,)
    log_birth = poisson_log_pmf(N1 - 1, jnp.asarray(birth_mean, dtype))
    lag = n[:, None] - n[None, :]  # (n, j)
    log_conv = jnp.where(lag >= 0, log_birth[jnp.maximum(lag, 0)] + log_pi[None, :], -jnp.inf)
    log_pred, log_total = _normalize_log(_lse(log_conv, axis=1))
    tail = jnp.maximum(-jnp.expm1(jnp.where(jnp.isfinite(log_total), log_total, 0.0)), 0.0)
    return log_pred, tail


def log_upsilon(
    log_e: Array, n_z: ArrayLike, u: int, clutter_rate: ArrayLike, detection_prob: ArrayLike, n_max: int
) -> Array:
    """``log Upsilon^u(n)``, ``n = 0 .. N_max``, with the ESF of the *normalised* ``Lambda / (1^T w)``.

    ``sum_{j} exp(-lambda_c) lambda_c^{m_z - j} P^n_{j+u} (1 - P_D)^{n - j - u} e_j(Lambda / W)``:
    the paper's ``Upsilon^u[w, Z](n)`` times ``W^u`` (Poisson clutter:
    ``(m_z - j)! p_K(m_z - j) = exp(-lambda_c) lambda_c^{m_z - j}``).

    Args:
        log_e: ``(J,)`` ``log e_j``, ``j = 0 .. J - 1`` (``-inf`` beyond the set's size).
        n_z: ``()`` int, ``|Z|``, the size of the set ``e`` was computed from.
        u: static ``0`` or ``1``.
        clutter_rate: ``()`` ``lambda_c``.
        detection_prob: ``()`` ``P_D``.
        n_max: static ``N_max``.

    Returns:
        ``(N_max + 1,)``.
    """
    log_e = jnp.asarray(log_e)
    dtype = log_e.dtype
    lam = jnp.asarray(clutter_rate, dtype)
    p_d = jnp.asarray(detection_prob, dtype)
    j = jnp.arange(log_e.shape[-1])[None, :]
    n = jnp.arange(n_max + 1)[:, None]
    n_clutter = n_z - j
    log_clutter = jnp.where(n_clutter >= 0, -lam + _xlog(jnp.maximum(n_clutter, 0), lam), -jnp.inf)
    i = j + u
    ok = i <= n
    rest = jnp.where(ok, n - i, 0)
    log_perm = jnp.where(ok, (gammaln(n + 1.0) - gammaln(rest + 1.0)).astype(dtype), -jnp.inf)
    terms = log_clutter + log_perm + _xlog(rest, 1.0 - p_d) + log_e[None, :]
    return _lse(terms, axis=1)
