"""Shared types and plumbing of the Gaussian local filters.

Two layers:

* **Component level** — a :class:`LocalFilter` is a NamedTuple of pure functions over one Gaussian
  (``init``, ``predict``, ``update``, ``moments``) whose noise is passed *per call* as a
  ``(mean, cov)`` pair. A Gaussian sum filter ``vmap``-s one local filter over mixture components
  × noise components; the GM noise components of the papers have non-zero means, so every
  local filter takes a noise mean.
* **Model level** — :func:`from_local` wraps a local filter into the one
  :class:`~gmjax.filters.base.Filter` contract, reading the noises and the prior from
  :class:`~gmjax.models.ModelParams` at every call.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, cast

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax import mixture as gmm
from gmjax._types import Array, Matrix, PRNGKey, Vector
from gmjax.filters.base import Filter, StepFlags, StepInfo, StepInputs
from gmjax.mixture import GaussianMixture
from gmjax.models.base import ModelParams, StateSpaceModel, call_convention, wrap_angles

__all__ = [
    "circular_mean",
    "wrap_angles",
    "GaussianState",
    "SqrtState",
    "UpdateInfo",
    "LocalFilter",
    "from_local",
    "gaussian_moments",
    "safe_chol",
]

_LOG_2PI = gaussian._LOG_2PI  # log(2 pi): one definition


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
        loglik: ``()`` ``log N(z; z_hat, S)``, the measurement log-likelihood (0 for a
            non-finite measurement). Gaussian sum filters re-weight components with it.
        innovation: ``(m,)`` ``z - z_hat`` (0 for a non-finite measurement).
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
            ``x' = f(x, t) + v``, ``v ~ N(noise_mean, noise_cov)``; ``t`` is the step's
            :class:`~gmjax.filters.StepInputs` (model-level filters pass it whole) or a bare time.
        update: ``(state, z (m,), t, noise_mean (m,), noise_cov (m, m)) -> (state, UpdateInfo)``
            for ``z = h(x, t) + w``, ``w ~ N(noise_mean, noise_cov)``.
        moments: ``state -> (mean (d,), cov (d, d))``.
    """

    init: Callable[[Array, Array], Any]
    predict: Callable[..., Any]
    update: Callable[..., tuple[Any, UpdateInfo]]
    moments: Callable[[Any], tuple[Array, Array]]


# ---------------------------------------------------------------------------------------------
# Small numerical helpers shared by the local filters.


def gaussian_state_moments(state: GaussianState) -> tuple[Vector, Matrix]:
    return state.mean, state.cov


def gaussian_state_init(mean, cov) -> GaussianState:
    mean = jnp.asarray(mean)
    return GaussianState(mean, gaussian.symmetrize(jnp.asarray(cov, mean.dtype)))


def is_missing(z: Array) -> Array:
    """``()`` bool: the measurement has a non-finite entry (NaN or ``±inf``): a predict-only step.

    The one place every filter decides "missing"; the step then raises
    ``StepFlags.nonfinite_measurement``.
    """
    return ~jnp.all(jnp.isfinite(jnp.asarray(z)))


def loglik_from_chol(y: Vector, L: Matrix) -> Array:
    """``log N(y; 0, L L^T)`` from a lower Cholesky factor (diagonal sign-agnostic)."""
    r = gaussian.solve_lower(L, y)
    m = y.shape[-1]
    return -0.5 * (m * _LOG_2PI + jnp.sum(r * r)) - jnp.sum(jnp.log(jnp.abs(jnp.diagonal(L))))


# One repaired Cholesky for the whole package (Gershgorin jitter, unrolled for small d, flagged).
safe_chol = gaussian.safe_cholesky


def repair_cov(cov: Matrix) -> tuple[Matrix, Array]:
    """Symmetrise ``cov``; if it is not numerically PD, add the safe factor's jitter to the diagonal
    (:func:`gmjax.gaussian.repair_spd`).

    Returns:
        ``(cov, repaired)``.
    """
    return gaussian.repair_spd(cov)


def kalman_gain(Pxz: Matrix, L_S: Matrix) -> Matrix:
    """``K = Pxz S^{-1}`` with ``S = L_S L_S^T`` (two triangular solves, no inverse)."""
    return gaussian.cho_solve_small(L_S, Pxz.T).T


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


def circular_mean(Z: Array, wm: Array, angle_dims: tuple[int, ...]) -> Array:
    """``sum_i wm_i Z_i`` ``(m,)``, with the ``angle_dims`` averaged on the circle.

    Angles are averaged as ``ref + sum_i wm_i wrap(Z_i - ref)`` around the first point ``ref``
    (exact for any weights, negative unscented weights included, while the points span less than
    ``pi`` around ``ref``), then wrapped into ``[-pi, pi)``.
    """
    if not angle_dims:
        return wm @ Z
    ref = Z[0]
    return wrap_angles(ref + wm @ wrap_angles(Z - ref, angle_dims), angle_dims)


def safe_z(z: Array, z_hat: Array) -> tuple[Array, Array]:
    """``(missing, z replaced by z_hat when missing)`` so nothing non-finite reaches the arithmetic."""
    z = jnp.asarray(z)
    missing = is_missing(z)
    return missing, jnp.where(missing, z_hat, z)


# ---------------------------------------------------------------------------------------------
# Model validation and the model-level wrapper.


def _is_concrete(tree) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def _output_shape(model: StateSpaceModel, name: str, fn, x, inputs):
    """``jax.eval_shape`` of a model function; ``None`` when it needs a control or other inputs that
    only the run provides (its shape is then checked when the filter is first traced)."""
    try:
        return jax.eval_shape(fn, x, inputs)
    except Exception:
        if call_convention(getattr(model, name), model.call, name) == "t":
            raise
        return None


def check_model(model: StateSpaceModel) -> tuple[int, int]:
    """Eagerly validate a model: noise/prior dims, ``f``/``h`` output shapes, PD covariances.

    Returns:
        ``(d, m)``.

    Raises:
        ValueError: naming the offending field.
    """
    if not isinstance(model, StateSpaceModel):
        raise ValueError(f"model: expected a StateSpaceModel, got {type(model).__name__}")
    for name in ("f", "h"):
        call_convention(getattr(model, name), model.call, name)  # raises on a bad `call`
    if not isinstance(model.state_dependent_noise, bool):
        raise ValueError(f"model.state_dependent_noise: expected a bool, got {model.state_dependent_noise!r}")
    if model.state_dependent_noise and model.process_noise_at is None:
        raise ValueError("model.state_dependent_noise: True needs a process_noise_at(noise, inputs, x)")
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
    inputs = StepInputs(t=cast(Array, jax.ShapeDtypeStruct((), jnp.int32)))
    f, h, _, _ = model.step_fns()
    fo = _output_shape(model, "f", f, x, inputs)
    if fo is not None and getattr(fo, "shape", None) != (d,):
        raise ValueError(f"model.f: must map a ({d},) state to ({d},), returned {fo.shape}")
    ho = _output_shape(model, "h", h, x, inputs)
    if ho is not None and getattr(ho, "shape", None) != (m,):
        raise ValueError(f"model.h: returns shape {ho.shape}, but model.measurement_noise has dimension {m}")
    angles = tuple(model.angle_dims)
    if any(isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < m for i in angles) or len(
        set(angles)
    ) != len(angles):
        raise ValueError(f"model.angle_dims: expected distinct measurement indices in [0, {m}), got {angles}")
    return d, m


def gaussian_moments(dist: Any) -> tuple[Array, Array]:
    """``(mean (d,), cov (d, d))`` of a noise or prior given as a :class:`GaussianMixture` (its
    moments, the best single-Gaussian KL fit) or as a :class:`GaussianState` / ``(mean, cov)`` pair."""
    if isinstance(dist, GaussianMixture):
        return gmm.moments(dist)
    mean, cov = dist
    return jnp.asarray(mean), jnp.asarray(cov)


def local_step_info(local: LocalFilter, state: Any, info: UpdateInfo, z: Array) -> StepInfo:
    """The :class:`StepInfo` of a single-Gaussian filter after ``local.update`` with measurement ``z``.

    ``extra`` holds ``innovation`` ``(m,)`` and ``innovation_cov`` ``(m, m)``.
    """
    mean, cov = local.moments(state)
    no = jnp.zeros((), bool)
    flags = StepFlags(info.repaired, no, no, is_missing(z))
    extra = {"innovation": info.innovation, "innovation_cov": info.innovation_cov}
    return StepInfo(mean, cov, info.loglik, jnp.ones((), jnp.int32), flags, None, extra)


def from_local(model: StateSpaceModel, local: LocalFilter) -> Filter:
    """Wrap a :class:`LocalFilter` into a :class:`Filter` over the model's parameters.

    ``filter.params`` is ``model.params`` (:class:`~gmjax.models.ModelParams`). Single-Gaussian
    filters moment-match a GM prior and GM noises: the prior is replaced by
    ``N(mean(prior), cov(prior))`` and each noise by its mean and covariance
    (:func:`gaussian_moments`), the best single-Gaussian (KL-projection) fit. A state-dependent
    process noise (``process_noise_at(noise, inputs, x)``) is evaluated at the mean the step
    predicts from (for every local filter, sigma-point ones included).
    """

    def init(params: ModelParams, prior: Any = None, *, key: PRNGKey | None = None):
        del key
        return local.init(*gaussian_moments(params.prior if prior is None else prior))

    def predict(params: ModelParams, state, inputs: StepInputs, *, key: PRNGKey | None = None):
        del key
        # a state-dependent noise at the mean predicted from (docstring of StateSpaceModel.noise_at)
        x = local.moments(state)[0] if model.state_dependent_noise else None
        noise = model.noise_at(params.process_noise, inputs, x)
        return local.predict(state, inputs, *gaussian_moments(noise))

    def update(params: ModelParams, state, z, inputs: StepInputs, *, key: PRNGKey | None = None):
        del key
        new, info = local.update(state, z, inputs, *gaussian_moments(params.measurement_noise))
        return new, local_step_info(local, new, info, z)

    return Filter(init, predict, update, model.params)
