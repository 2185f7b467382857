"""The linear Gaussian system of Zhang et al. (PCRB from Gaussian mixtures; seed 002 §V-A, eqs 74-75).

Returns a :class:`gmjax.pcrb.PCRBModel` (additive Gaussian noises, the paper's time convention
``x_{n+1} = f(x_n, n) + w_n``, ``z_{n+1} = h(x_{n+1}, n+1) + v_{n+1}``).
"""

from __future__ import annotations

import jax.numpy as jnp

from gmjax._types import ArrayLike, DTypeLike
from gmjax.mixture import from_gaussian
from gmjax.pcrb import PCRBModel

__all__ = ["linear_system"]


def linear_system(
    F: ArrayLike,
    H: ArrayLike,
    Q: ArrayLike,
    R: ArrayLike,
    m0: ArrayLike,
    P0: ArrayLike,
    *,
    dtype: DTypeLike | None = None,
) -> PCRBModel:
    """The linear Gaussian model of seed 002 §V-A (eqs 74-75), time-invariant.

    ``x_{n+1} = F x_n + w_n``, ``z_{n+1} = H x_{n+1} + v_{n+1}``, ``x_0 ~ N(m0, P0)``. Jacobians are
    the constant matrices.
    """
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    F = jnp.asarray(F, dtype)
    H = jnp.asarray(H, dtype)
    d = F.shape[-1]
    if F.shape != (d, d):
        raise ValueError(f"F: expected a square matrix, got shape {F.shape}")
    if H.ndim != 2 or H.shape[1] != d:
        raise ValueError(f"H: expected shape (m, {d}), got {H.shape}")
    return PCRBModel(
        f=lambda x, n: F @ x,
        h=lambda x, n: H @ x,
        Q=jnp.asarray(Q, dtype),
        R=jnp.asarray(R, dtype),
        prior=from_gaussian(jnp.asarray(m0, dtype), jnp.asarray(P0, dtype)),
        f_jacobian=lambda x, n: F,
        h_jacobian=lambda x, n: H,
    )
