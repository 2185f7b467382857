"""The model a PCRB computation needs: additive white Gaussian noises (seed 002 eqs 1-2).

gmjax's :class:`~gmjax.models.StateSpaceModel` writes ``x_k = f(x_{k-1}, k) + v_k`` with
Gaussian-mixture noises; the PCRB recursion of Tichavsky et al. (seed 002 eqs 4-8) needs single
zero-mean Gaussian noises with covariances ``Q`` and ``R`` and is written with the index of the
*input* state. :class:`PCRBModel` keeps the paper's convention exactly; :func:`from_state_space_model`
converts (and checks) a :class:`StateSpaceModel`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import mixture as gmm
from gmjax._types import Array, ArrayLike
from gmjax.mixture import GaussianMixture
from gmjax.pcrb._noise import noise_information

if TYPE_CHECKING:  # gmjax.models imports nothing from pcrb, but keep the import graph one-way
    from gmjax.models.base import StateSpaceModel

__all__ = ["PCRBModel", "from_state_space_model", "prior_information", "as_pcrb_model"]


class PCRBModel(NamedTuple):
    """``x_{n+1} = f(x_n, n) + w_n``, ``z_{n+1} = h(x_{n+1}, n+1) + v_{n+1}`` (seed 002 eqs 1-2).

    Time-index convention: ``f(x, n)`` maps the state with index ``n`` to the state with index
    ``n + 1`` (``f_n`` of eq 1) and ``h(x, n)`` is the measurement function of the state with index
    ``n`` (``h_n``); the first measurement is ``z_1 = h(x_1, 1) + v_1``. ``w_n ~ N(0, Q)``,
    ``v_n ~ N(0, R)`` (constant covariances), and ``x_0 ~ prior``. Every ``pcrb`` entry point also
    accepts a :class:`~gmjax.models.StateSpaceModel` (its ``f(x, k)`` maps ``x_{k-1}`` to ``x_k``)
    and converts it with :func:`from_state_space_model`; either way ``bound[k]`` is the bound of
    ``x_k``, the state that ``gmjax.filters.run`` (default times ``1..T``) reports in ``states[k-1]``.

    Noises may be Gaussian mixtures (non-Gaussian additive noise): the recursion then uses the
    noise's Fisher information (:func:`gmjax.pcrb.noise_information`) in place of ``Q^{-1}`` and
    ``R^{-1}``, and the Monte Carlo PCRB samples the mixture.

    Attributes:
        f: ``f(x (d,), n) -> (d,)`` traceable.
        h: ``h(x (d,), n) -> (m,)`` traceable.
        Q: ``(d, d)`` process-noise covariance (non-singular), or a :class:`GaussianMixture`.
        R: ``(m, m)`` measurement-noise covariance (non-singular), or a :class:`GaussianMixture`.
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
        return self.Q.dim if isinstance(self.Q, GaussianMixture) else int(np.shape(self.Q)[-1])

    @property
    def measurement_dim(self) -> int:
        return self.R.dim if isinstance(self.R, GaussianMixture) else int(np.shape(self.R)[-1])

    def process_information(self, dtype: Any = None) -> Array:
        """``(d, d)`` Fisher information of the process noise (``Q^{-1}`` when Gaussian)."""
        return noise_information(self.Q, dtype=dtype or self.prior.means.dtype)

    def measurement_information(self, dtype: Any = None) -> Array:
        """``(m, m)`` Fisher information of the measurement noise (``R^{-1}`` when Gaussian)."""
        return noise_information(self.R, dtype=dtype or self.prior.means.dtype)

    def sample_process_noise(self, key: Array, n: int, dtype: Any) -> Array:
        """``(n, d)`` draws of ``w``."""
        if isinstance(self.Q, GaussianMixture):
            return gmm.sample(self.Q, key, n).astype(dtype)
        Q = jnp.asarray(self.Q, dtype)
        return jax.random.normal(key, (n, Q.shape[-1]), dtype) @ jnp.linalg.cholesky(Q).T

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
        raise ValueError(f"model: expected a PCRBModel or a StateSpaceModel, got {type(model).__name__}")
    for name in ("Q", "R"):
        gm = getattr(model, name)
        if isinstance(gm, GaussianMixture):
            try:
                gmm.check(gm)
            except ValueError as e:
                raise ValueError(f"{name}: {e}") from None
    Q = _moment_cov(model.Q)
    R = _moment_cov(model.R)
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
        raise ValueError(f"prior: dimension {model.prior.dim} does not match Q of shape {Q.shape}")
    return model


def _moment_cov(noise) -> np.ndarray:
    if isinstance(noise, GaussianMixture):
        return np.asarray(gmm.moments(noise)[1], np.float64)
    return np.asarray(noise, np.float64)


def as_pcrb_model(model: Any) -> PCRBModel:
    """A :class:`PCRBModel`, converting a :class:`~gmjax.models.StateSpaceModel` (one convention
    for the user: the filters' ``StateSpaceModel``); checked."""
    from gmjax.models.base import StateSpaceModel

    if isinstance(model, StateSpaceModel):
        model = from_state_space_model(model)
    return check_model(model)


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
    """Convert a :class:`gmjax.models.StateSpaceModel` (Gaussian or Gaussian-mixture noises).

    ``StateSpaceModel`` writes ``x_k = f(x_{k-1}, k) + v_k``: its ``f`` is called with the index of
    the *output* state, so the PCRB model's ``f(x, n)`` is ``ssm.f(x, n + 1)``. Measurements keep
    their index. A single zero-mean Gaussian noise becomes its covariance; any other noise (several
    components, or a mean) stays a mixture, and the recursion uses its Fisher information. The model
    must be time-invariant in its noise (``process_noise_at`` is not used) and free of controls.

    Raises:
        ValueError: a model with a control input (``f(x, u, t)``).
    """
    from gmjax.models.base import call_convention

    if call_convention(ssm.f, ssm.call) == "u,t":
        raise ValueError("model: the PCRB has no control input; fix u inside f")
    noises = {}
    for name in ("process_noise", "measurement_noise"):
        gm = getattr(ssm, name)
        mask = np.asarray(gm.mask)
        k = int(np.flatnonzero(mask)[0]) if mask.sum() == 1 else -1
        if k >= 0 and not np.any(np.asarray(gm.means)[k] != 0):
            noises[name] = jnp.asarray(gm.covs)[k]
        else:
            noises[name] = gm
    f_ssm, h_ssm, fj, hj = ssm.step_fns()
    return PCRBModel(
        f=lambda x, n: f_ssm(x, n + 1),
        h=h_ssm,
        Q=noises["process_noise"],
        R=noises["measurement_noise"],
        prior=ssm.prior,
        f_jacobian=None if fj is None else (lambda x, n: fj(x, n + 1)),
        h_jacobian=hj,
    )
