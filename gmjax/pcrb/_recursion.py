"""Tichavsky's PCRB recursion (seed 002 eqs 4-8) and its linear special case (§V-A)."""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve

from gmjax import gaussian
from gmjax._types import Array, ArrayLike
from gmjax.mixture import GaussianMixture
from gmjax.pcrb._noise import noise_information

__all__ = ["PCRBResult", "pcrb_step", "pcrb_linear", "bounds_from_information"]


class PCRBResult(NamedTuple):
    """Per-step Fisher information and bounds, index 0 being ``x_0``.

    Attributes:
        information: ``(T + 1, d, d)`` ``J_n`` for ``n = 0..T``.
        bound: ``(T + 1, d, d)`` ``J_n^{-1}``, the PCRB of ``x_n`` (eq 3).
        info: method-specific diagnostics (a NamedTuple or ``None``).
    """

    information: Array
    bound: Array
    info: object = None


def pcrb_step(J: ArrayLike, D11: ArrayLike, D12: ArrayLike, D22: ArrayLike) -> Array:
    """One step of eq 4: ``J_{n+1} = D22 - D21 (J_n + D11)^{-1} D12`` with ``D21 = D12^T`` (eq 7).

    Args:
        J: ``(d, d)`` FIM of ``x_n``. D11, D12, D22: ``(d, d)`` expectations of eqs 5, 6, 8.

    Returns:
        ``(d, d)`` FIM of ``x_{n+1}`` (symmetrised).
    """
    J, D11, D12, D22 = (jnp.asarray(a) for a in (J, D11, D12, D22))
    A = gaussian.symmetrize(J + D11)
    X = jnp.linalg.solve(A, D12)
    return gaussian.symmetrize(D22 - D12.T @ X)


def inv_pd(M: ArrayLike) -> Array:
    """Inverse of a symmetric positive definite matrix via a plain Cholesky factor (validated
    inputs such as ``Q``, ``R`` and FIMs; cheaper to compile than a repairing factorisation)."""
    M = gaussian.symmetrize(jnp.asarray(M))
    L = jnp.linalg.cholesky(M)
    return gaussian.symmetrize(cho_solve((L, True), jnp.eye(M.shape[-1], dtype=M.dtype)))


@jax.jit
def bounds_from_information(J: ArrayLike) -> Array:
    """``J^{-1}`` over the last two axes (symmetrised)."""
    return gaussian.symmetrize(jnp.linalg.inv(jnp.asarray(J)))


def _stack(M: Array, n_steps: int, name: str, shape: tuple[int, int]) -> Array:
    if M.ndim == 2:
        if M.shape != shape:
            raise ValueError(f"{name}: expected shape {shape} or (T, *{shape}), got {M.shape}")
        return jnp.broadcast_to(M, (n_steps,) + shape)
    if M.shape != (n_steps,) + shape:
        raise ValueError(f"{name}: expected shape {(n_steps,) + shape}, got {M.shape}")
    return M


def pcrb_linear(
    F: ArrayLike,
    H: ArrayLike,
    Q: ArrayLike | GaussianMixture,
    R: ArrayLike | GaussianMixture,
    P0: ArrayLike,
    n_steps: int,
) -> PCRBResult:
    """PCRB of the linear Gaussian model ``x_{n+1} = F_n x_n + w_n``, ``z_{n+1} = H_{n+1} x_{n+1} + v``.

    With ``D11 = F^T Q^{-1} F``, ``D12 = -F^T Q^{-1}``, ``D22 = Q^{-1} + H^T R^{-1} H`` (seed 002
    eqs 76-78) the recursion of eq 4 is the information form of the Kalman/Riccati recursion, so
    ``J_n^{-1}`` equals the Kalman filter's posterior covariance.

    With Gaussian-mixture noises (non-Gaussian additive noise) ``Q^{-1}`` and ``R^{-1}`` become the
    noises' Fisher informations (:func:`gmjax.pcrb.noise_information`); the bound is then below the
    (Gaussian-sum) filters' error covariance, no longer equal to a Kalman covariance.

    Args:
        F: ``(d, d)`` or ``(T, d, d)`` (``F[n]`` maps ``x_n`` to ``x_{n+1}``).
        H: ``(m, d)`` or ``(T, m, d)`` (``H[n]`` is ``H_{n+1}``, the measurement of ``x_{n+1}``).
        Q: ``(d, d)`` or ``(T, d, d)``, or a :class:`~gmjax.mixture.GaussianMixture` (time-invariant).
        R: ``(m, m)`` or ``(T, m, m)``, or a :class:`~gmjax.mixture.GaussianMixture`.
        P0: ``(d, d)`` prior covariance.
        n_steps: ``T`` (static).

    Returns:
        :class:`PCRBResult` with ``T + 1`` entries.
    """
    P0 = jnp.asarray(P0)
    Qi = _information(Q, P0.dtype)
    Ri = _information(R, P0.dtype)
    return _pcrb_linear(F, H, Qi, Ri, P0, int(n_steps))


def _information(noise, dtype):
    """``Q^{-1}`` per step (``(d, d)`` or ``(T, d, d)``) or a mixture's Fisher information."""
    if isinstance(noise, GaussianMixture):
        return noise_information(noise, dtype=dtype)
    M = jnp.asarray(noise, dtype)
    if M.ndim == 3:
        return jax.vmap(inv_pd)(M)
    return inv_pd(M) if M.ndim == 2 else M


@partial(jax.jit, static_argnames=("n_steps",))
def _pcrb_linear(F, H, Qi, Ri, P0, n_steps: int) -> PCRBResult:
    P0 = jnp.asarray(P0)
    d = P0.shape[-1]
    H = jnp.asarray(H, P0.dtype)
    m = H.shape[-2]
    F = _stack(jnp.asarray(F, P0.dtype), n_steps, "F", (d, d))
    H = _stack(H, n_steps, "H", (m, d))
    Qi = _stack(jnp.asarray(Qi, P0.dtype), n_steps, "Q", (d, d))
    Ri = _stack(jnp.asarray(Ri, P0.dtype), n_steps, "R", (m, m))
    J0 = inv_pd(P0)

    def step(J, inputs):
        Fn, Hn, Qi, Ri = inputs
        D11 = Fn.T @ Qi @ Fn
        D12 = -Fn.T @ Qi
        D22 = Qi + Hn.T @ Ri @ Hn
        Jn = pcrb_step(J, D11, D12, D22)
        return Jn, Jn

    _, Js = jax.lax.scan(step, J0, (F, H, Qi, Ri))
    Js = jnp.concatenate([J0[None], Js])
    return PCRBResult(Js, bounds_from_information(Js), None)
