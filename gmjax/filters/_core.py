"""Shared types and plumbing of the Gaussian local filters (DESIGN §3).

Two layers:

* **Component level** — a :class:`LocalFilter` is a NamedTuple of pure functions over one Gaussian
  (``init``, ``predict``, ``update``, ``moments``) whose noise is passed *per call* as a
  ``(mean, cov)`` pair. A Gaussian sum filter ``vmap``-s one local filter over mixture components
  × noise components; the GM noise components of the papers have non-zero means, so every
  local filter takes a noise mean.
* **Model level** — a :class:`Filter` (``init(prior_gm)``, ``predict(state, t)``,
  ``update(state, z, t)``) built from a :class:`gmjax.models.StateSpaceModel`, and :func:`run`,
  a ``lax.scan`` over a measurement sequence.

Time indexing of :func:`run`: the initial state describes ``x_0``; step ``k = 0 .. T-1`` predicts
with ``f(., ts[k])`` to time ``ts[k]`` and then updates with ``zs[k]`` through ``h(., ts[k])``, so
``states[k]`` is the posterior of ``x_{ts[k]}`` given ``zs[:k+1]``. The default ``ts`` is
``1, 2, ..., T`` (matching ``x_k = f(x_{k-1}, k)`` in :class:`StateSpaceModel`). A measurement
containing any NaN is skipped (predict-only step, log-likelihood 0).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve, solve_triangular

from gmjax import gaussian
from gmjax import mixture as gmm
from gmjax._types import Array, Matrix, Vector
from gmjax.mixture import GaussianMixture
from gmjax.models._base import StateSpaceModel

__all__ = [
    "GaussianState",
    "SqrtState",
    "UpdateInfo",
    "LocalFilter",
    "Filter",
    "run",
    "from_local",
    "safe_chol",
]

_LOG_2PI = 1.8378770664093453


class GaussianState(NamedTuple):
    """Mean ``(d,)`` and covariance ``(d, d)`` of one Gaussian."""

    mean: Vector
    cov: Matrix


class SqrtState(NamedTuple):
    """Mean ``(d,)`` and lower Cholesky factor ``(d, d)`` (``cov = chol @ chol.T``), for ``sckf``."""

    mean: Vector
    chol: Matrix


class UpdateInfo(NamedTuple):
    """What a measurement update reports.

    Attributes:
        loglik: ``()`` ``log N(z; z_hat, S)``, the measurement log-likelihood (0 for a NaN
            measurement). Gaussian sum filters re-weight components with it.
        innovation: ``(m,)`` ``z - z_hat`` (0 for a NaN measurement).
        innovation_cov: ``(m, m)`` ``S``.
        repaired: ``()`` bool, True when a covariance (predicted, innovation or posterior)
            was not numerically positive definite and was repaired by symmetrising and adding
            jitter (:func:`gmjax.gaussian.safe_cholesky`).
    """

    loglik: Array
    innovation: Vector
    innovation_cov: Matrix
    repaired: Array


class LocalFilter(NamedTuple):
    """A Kalman-type filter for one Gaussian, with the noise given per call.

    Attributes:
        init: ``(mean (d,), cov (d, d)) -> state``.
        predict: ``(state, t, noise_mean (d,), noise_cov (d, d)) -> state`` for
            ``x' = f(x, t) + v``, ``v ~ N(noise_mean, noise_cov)``.
        update: ``(state, z (m,), t, noise_mean (m,), noise_cov (m, m)) -> (state, UpdateInfo)``
            for ``z = h(x, t) + w``, ``w ~ N(noise_mean, noise_cov)``.
        moments: ``state -> (mean (d,), cov (d, d))``.
    """

    init: Callable[[Array, Array], Any]
    predict: Callable[..., Any]
    update: Callable[..., tuple[Any, UpdateInfo]]
    moments: Callable[[Any], tuple[Array, Array]]


class Filter(NamedTuple):
    """A model-level filter (DESIGN §3): pure functions over a filter state.

    Attributes:
        init: ``(prior: GaussianMixture | None = None) -> state``; ``None`` uses the model prior.
        predict: ``(state, t) -> state``.
        update: ``(state, z (m,), t) -> (state, info)``; an all-NaN / any-NaN ``z`` is skipped.
        moments: optional ``state -> (mean (d,), cov (d, d))`` of the filter's estimate.
    """

    init: Callable[..., Any]
    predict: Callable[[Any, Array], Any]
    update: Callable[[Any, Array, Array], tuple[Any, Any]]
    moments: Callable[[Any], tuple[Array, Array]] | None = None


# ---------------------------------------------------------------------------------------------
# Small numerical helpers shared by the local filters.


def gaussian_state_moments(state: GaussianState) -> tuple[Vector, Matrix]:
    return state.mean, state.cov


def gaussian_state_init(mean, cov) -> GaussianState:
    mean = jnp.asarray(mean)
    return GaussianState(mean, gaussian.symmetrize(jnp.asarray(cov, mean.dtype)))


def is_missing(z: Array) -> Array:
    """``()`` bool: the measurement holds a NaN (predict-only step)."""
    return jnp.any(jnp.isnan(z))


def loglik_from_chol(y: Vector, L: Matrix) -> Array:
    """``log N(y; 0, L L^T)`` from a lower Cholesky factor (diagonal sign-agnostic)."""
    r = solve_triangular(L, y, lower=True)
    m = y.shape[-1]
    return -0.5 * (m * _LOG_2PI + jnp.sum(r * r)) - jnp.sum(jnp.log(jnp.abs(jnp.diagonal(L))))


# One repaired Cholesky for the whole package (Gershgorin jitter, unrolled for small d, flagged).
safe_chol = gaussian.safe_cholesky


def repair_cov(cov: Matrix) -> tuple[Matrix, Array]:
    """Symmetrise ``cov``; if it is not numerically PD, replace it by ``L L^T`` of the safe factor.

    Returns:
        ``(cov, repaired)``.
    """
    cov = gaussian.symmetrize(cov)
    res = safe_chol(cov)
    fixed = res.factor @ res.factor.T
    return jnp.where(res.repaired, fixed, cov), res.repaired


def kalman_gain(Pxz: Matrix, L_S: Matrix) -> Matrix:
    """``K = Pxz S^{-1}`` with ``S = L_S L_S^T`` (two triangular solves, no inverse)."""
    return cho_solve((L_S, True), Pxz.T).T


def select_state(missing: Array, old: Any, new: Any) -> Any:
    """``old`` where the measurement is missing, else ``new`` (leaf-wise ``jnp.where``)."""
    return jax.tree_util.tree_map(lambda a, b: jnp.where(missing, a, b), old, new)


def finish_info(missing, loglik, innovation, S, repaired) -> UpdateInfo:
    return UpdateInfo(
        loglik=jnp.where(missing, jnp.zeros_like(loglik), loglik),
        innovation=jnp.where(missing, jnp.zeros_like(innovation), innovation),
        innovation_cov=S,
        repaired=jnp.where(missing, False, repaired),
    )


def safe_z(z: Array, z_hat: Array) -> tuple[Array, Array]:
    """``(missing, z with NaNs replaced by z_hat)`` so nothing NaN reaches the arithmetic."""
    z = jnp.asarray(z)
    missing = is_missing(z)
    return missing, jnp.where(missing, z_hat, z)


# ---------------------------------------------------------------------------------------------
# Model validation and the model-level wrapper.


def _is_concrete(tree) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def check_model(model: StateSpaceModel) -> tuple[int, int]:
    """Eagerly validate a model: noise/prior dims, ``f``/``h`` output shapes, PD covariances.

    Returns:
        ``(d, m)``.

    Raises:
        ValueError: naming the offending field.
    """
    if not isinstance(model, StateSpaceModel):
        raise ValueError(f"model: expected a StateSpaceModel, got {type(model).__name__}")
    for name in ("process_noise", "measurement_noise", "prior"):
        gm = getattr(model, name)
        if not isinstance(gm, GaussianMixture):
            raise ValueError(f"model.{name}: expected a GaussianMixture, got {type(gm).__name__}")
        if _is_concrete(gm):
            try:
                gmm.check(gm)
            except ValueError as e:
                raise ValueError(f"model.{name}: {e}") from None
    d = model.prior.dim
    m = model.measurement_noise.dim
    if model.process_noise.dim != d:
        raise ValueError(
            f"model.process_noise: dimension {model.process_noise.dim} does not match the state "
            f"dimension {d} of model.prior"
        )
    x = jax.ShapeDtypeStruct((d,), model.prior.means.dtype)
    t = jax.ShapeDtypeStruct((), jnp.int32)
    fo = jax.eval_shape(model.f, x, t)
    if getattr(fo, "shape", None) != (d,):
        raise ValueError(f"model.f: must map a ({d},) state to ({d},), returned {fo.shape}")
    ho = jax.eval_shape(model.h, x, t)
    if getattr(ho, "shape", None) != (m,):
        raise ValueError(
            f"model.h: returns shape {ho.shape}, but model.measurement_noise has dimension {m}"
        )
    return d, m


def from_local(model: StateSpaceModel, local: LocalFilter) -> Filter:
    """Wrap a :class:`LocalFilter` into a model-level :class:`Filter`.

    Single-Gaussian filters moment-match the GM prior and GM noises of the model: the prior is
    replaced by ``N(mean(prior), cov(prior))`` and each noise by its mean and covariance
    (:func:`gmjax.mixture.moments`), which is the best single-Gaussian (KL-projection) fit.
    """
    q_mean, q_cov = gmm.moments(model.process_noise)
    r_mean, r_cov = gmm.moments(model.measurement_noise)

    def init(prior: GaussianMixture | None = None):
        prior = model.prior if prior is None else prior
        mean, cov = gmm.moments(prior)
        return local.init(mean, cov)

    def predict(state, t):
        return local.predict(state, t, q_mean, q_cov)

    def update(state, z, t):
        return local.update(state, z, t, r_mean, r_cov)

    return Filter(init, predict, update, local.moments)


def check_sequence(zs: Array, ts: Array | None) -> tuple[Array, Array]:
    """Validate a measurement sequence ``zs`` ``(T, m)`` and its times ``ts`` ``(T,)`` (default ``1..T``)."""
    zs = jnp.asarray(zs)
    if zs.ndim != 2:
        raise ValueError(f"zs: expected shape (T, m), got {zs.shape}")
    T = zs.shape[0]
    ts = jnp.arange(1, T + 1, dtype=jnp.int32) if ts is None else jnp.asarray(ts)
    if ts.shape != (T,):
        raise ValueError(f"ts: expected shape ({T},) to match zs, got {ts.shape}")
    return zs, ts


def run(
    filter: Filter,
    zs: Array,
    ts: Array | None = None,
    *,
    prior: GaussianMixture | None = None,
    init_state: Any = None,
) -> tuple[Any, Any]:
    """Run a filter over a measurement sequence with ``lax.scan``.

    Step ``k`` predicts to time ``ts[k]`` and updates with ``zs[k]`` (see the module docstring);
    a row of ``zs`` holding a NaN is a predict-only step.

    Args:
        filter: a :class:`Filter` (any NamedTuple with ``init``, ``predict``, ``update``).
        zs: ``(T, m)`` measurements.
        ts: ``(T,)`` times passed to ``f`` and ``h``; default ``1, ..., T`` (int32).
        prior: prior mixture for ``filter.init`` (default: the model's).
        init_state: a ready initial state (e.g. a particle filter state that holds its key);
            overrides ``prior``.

    Returns:
        ``(states, infos)``: pytrees with a leading ``T`` axis; ``states[k]`` is the posterior at
        ``ts[k]``.
    """
    zs, ts = check_sequence(zs, ts)
    if init_state is None:
        init_state = filter.init() if prior is None else filter.init(prior)

    def step(state, zt):
        z, t = zt
        state = filter.predict(state, t)
        state, info = filter.update(state, z, t)
        return state, (state, info)

    _, (states, infos) = jax.lax.scan(step, init_state, (zs, ts))
    return states, infos
