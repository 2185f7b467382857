"""The model a PCRB computation needs: additive white Gaussian noises (seed 002 eqs 1-2).

gmjax's :class:`~gmjax.models.StateSpaceModel` writes ``x_k = f(x_{k-1}, k) + v_k`` with
Gaussian-mixture noises; the PCRB recursion of Tichavsky et al. (seed 002 eqs 4-8) needs single
zero-mean Gaussian noises with covariances ``Q`` and ``R`` and is written with the index of the
*input* state. :class:`PCRBModel` keeps the paper's convention exactly; :func:`from_state_space_model`
converts (and checks) a :class:`StateSpaceModel`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._types import Array, ArrayLike
from gmjax.mixture import GaussianMixture

if TYPE_CHECKING:  # gmjax.models imports nothing from pcrb, but keep the import graph one-way
    from gmjax.models.base import StateSpaceModel

__all__ = ["PCRBModel", "from_state_space_model", "prior_information"]


class PCRBModel(NamedTuple):
    """``x_{n+1} = f(x_n, n) + w_n``, ``z_{n+1} = h(x_{n+1}, n+1) + v_{n+1}`` (seed 002 eqs 1-2).

    Time-index convention: ``f(x, n)`` maps the state with index ``n`` to the state with index
    ``n + 1`` (``f_n`` of eq 1) and ``h(x, n)`` is the measurement function of the state with index
    ``n`` (``h_n``); the first measurement is ``z_1 = h(x_1, 1) + v_1``. ``w_n ~ N(0, Q)``,
    ``v_n ~ N(0, R)`` (constant covariances), and ``x_0 ~ prior``.

    Attributes:
        f: ``f(x (d,), n) -> (d,)`` traceable.
        h: ``h(x (d,), n) -> (m,)`` traceable.
        Q: ``(d, d)`` process-noise covariance (non-singular).
        R: ``(m, m)`` measurement-noise covariance (non-singular).
        prior: ``GaussianMixture`` of ``x_0``.
        f_jacobian, h_jacobian: optional ``(x, n) -> (d, d) / (m, d)``; default ``jax.jacfwd``.
    """

    f: Callable[[Array, Array], Array]
    h: Callable[[Array, Array], Array]
    Q: Array
    R: Array
    prior: GaussianMixture
    f_jacobian: Callable[[Array, Array], Array] | None = None
    h_jacobian: Callable[[Array, Array], Array] | None = None

    @property
    def state_dim(self) -> int:
        return int(np.shape(self.Q)[-1])

    @property
    def measurement_dim(self) -> int:
        return int(np.shape(self.R)[-1])

    def jac_f(self, x: Array, n: Array) -> Array:
        """``F_n(x) = df_n / dx^T`` ``(d, d)`` (eq 42)."""
        if self.f_jacobian is not None:
            return self.f_jacobian(x, n)
        return jax.jacfwd(self.f)(x, n)

    def jac_h(self, x: Array, n: Array) -> Array:
        """``H_n(x) = dh_n / dx^T`` ``(m, d)`` (eq 59)."""
        if self.h_jacobian is not None:
            return self.h_jacobian(x, n)
        return jax.jacfwd(self.h)(x, n)


def check_model(model: PCRBModel) -> PCRBModel:
    """Validate shapes and positive definiteness of ``Q`` and ``R`` eagerly (the API boundary)."""
    if not isinstance(model, PCRBModel):
        raise ValueError(f"model: expected a PCRBModel, got {type(model).__name__}")
    Q = np.asarray(model.Q, np.float64)
    R = np.asarray(model.R, np.float64)
    for name, M in (("Q", Q), ("R", R)):
        if M.ndim != 2 or M.shape[0] != M.shape[1]:
            raise ValueError(f"{name}: expected a square matrix, got shape {M.shape}")
        if not np.all(np.isfinite(M)):
            raise ValueError(f"{name}: contains NaN or inf")
        if not np.allclose(M, M.T, rtol=1e-8, atol=1e-12 * max(np.abs(M).max(), 1e-300)):
            raise ValueError(f"{name}: not symmetric")
        if np.linalg.eigvalsh(0.5 * (M + M.T))[0] <= 0:
            raise ValueError(f"{name}: not positive definite (the PCRB needs non-singular noise)")
    if model.prior.dim != Q.shape[0]:
        raise ValueError(
            f"prior: dimension {model.prior.dim} does not match Q of shape {Q.shape}"
        )
    return model


def prior_information(prior: GaussianMixture, J0: ArrayLike | None = None) -> Array:
    """The initial FIM ``J_0``: ``J0`` if given, else ``Sigma_0^{-1}`` for a one-component prior.

    Raises:
        ValueError: for a multi-component prior without ``J0`` (its FIM has no closed form), or a
            ``J0`` of the wrong shape.
    """
    d = prior.dim
    if J0 is not None:
        J0 = jnp.asarray(J0, prior.means.dtype)
        if J0.shape != (d, d):
            raise ValueError(f"J0: expected shape ({d}, {d}), got {J0.shape}")
        return J0
    live = np.asarray(prior.mask)
    if live.sum() != 1:
        raise ValueError(
            "J0: the prior has several components; pass J0 (e.g. the inverse covariance of the "
            "Gaussian the mixture was split from)"
        )
    P0 = jnp.asarray(prior.covs)[int(np.flatnonzero(live)[0])]
    return jnp.linalg.inv(P0)


def from_state_space_model(ssm: StateSpaceModel) -> PCRBModel:
    """Convert a :class:`gmjax.models.StateSpaceModel` with single zero-mean Gaussian noises.

    ``StateSpaceModel`` writes ``x_k = f(x_{k-1}, k) + v_k``: its ``f`` is called with the index of
    the *output* state, so the PCRB model's ``f(x, n)`` is ``ssm.f(x, n + 1)``. Measurements keep
    their index.

    Raises:
        ValueError: if either noise has more than one live component or a non-zero mean.
    """
    noises = {}
    for name in ("process_noise", "measurement_noise"):
        gm = getattr(ssm, name)
        mask = np.asarray(gm.mask)
        if mask.sum() != 1:
            raise ValueError(f"{name}: the PCRB recursion needs a single Gaussian, got {mask.sum()}")
        k = int(np.flatnonzero(mask)[0])
        if np.any(np.asarray(gm.means)[k] != 0):
            raise ValueError(f"{name}: the PCRB recursion needs zero-mean noise")
        noises[name] = jnp.asarray(gm.covs)[k]
    f_ssm, fj = ssm.f, ssm.f_jacobian
    return PCRBModel(
        f=lambda x, n: f_ssm(x, n + 1),
        h=ssm.h,
        Q=noises["process_noise"],
        R=noises["measurement_noise"],
        prior=ssm.prior,
        f_jacobian=None if fj is None else (lambda x, n: fj(x, n + 1)),
        h_jacobian=ssm.h_jacobian,
    )
