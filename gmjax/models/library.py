"""A library of motion and measurement models (Stone Soup's set as the reference).

Motion models map a state over a step of length ``dt`` and give the exactly discretised process-noise
covariance ``Q(dt)`` of their continuous-time white-noise model; measurement models give ``h(x)``,
the measurement covariance ``R`` and which measurement components are angles. Everything is a pure JAX
function, Jacobians come from ``jax.jacfwd`` (or are exact matrices for the linear models), and
:func:`state_space_model` assembles a motion and a measurement model into a
:class:`~gmjax.models.StateSpaceModel` whose process noise follows the step's ``dt``.

State ordering follows Stone Soup: per spatial axis, position then its derivatives
(``[x, vx, y, vy]`` for a 2-D constant-velocity model). Angles are in radians; bearing is
``atan2(y, x)`` measured from the x axis, elevation ``atan2(z, sqrt(x^2 + y^2))``.

Motion models (``q`` is the diffusion coefficient, Stone Soup's ``noise_diff_coeff``):

* :func:`constant_velocity`, :func:`constant_acceleration`, :func:`nth_derivative` (any spatial
  dimension): ``F_ij = dt^(j-i)/(j-i)!``, ``Q_ij = q dt^(2N+1-i-j) / ((N-i)! (N-j)! (2N+1-i-j))``.
* :func:`random_walk`: ``F = I``, ``Q = q dt I``.
* :func:`singer`: acceleration as a first-order Gauss-Markov process with damping ``alpha``
  (Singer 1970); the closed form of Stone Soup's ``Singer`` docstring.
* :func:`coordinated_turn`: known turn rate ``omega`` (Stone Soup's ``KnownTurnRate``), and
  :func:`coordinated_turn_unknown_rate` with the rate as the fifth state (``ConstantTurn``).

Measurement models: :func:`cartesian_position`, :func:`bearing_range` (Stone Soup's
``CartesianToBearingRange``: ``[bearing, range]``), :func:`elevation_bearing_range`
(``CartesianToElevationBearingRange``), :func:`bearings_only`, :func:`bearing_range_rate`
(``CartesianToBearingRangeRate`` in 2-D), and :func:`glint_mixture` (a two-component Gaussian mixture
for glint noise: a narrow core and a wide tail with the same mean, seed 000 §IV-D).
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._types import Array, ArrayLike
from gmjax.mixture import GaussianMixture

__all__ = [
    "MotionModel",
    "MeasurementModel",
    "nth_derivative",
    "constant_velocity",
    "constant_acceleration",
    "random_walk",
    "singer",
    "coordinated_turn",
    "coordinated_turn_unknown_rate",
    "cartesian_position",
    "bearing_range",
    "elevation_bearing_range",
    "bearings_only",
    "bearing_range_rate",
    "glint_mixture",
    "noise_scaler",
    "state_space_model",
]


class MotionModel(NamedTuple):
    """``x_k = f(x_{k-1}, dt) + v_k``, ``v_k ~ N(0, Q(dt))``.

    Attributes:
        f: ``(x (d,), dt ()) -> (d,)``, traceable.
        Q: ``dt () -> (d, d)``, the exactly discretised process-noise covariance.
        dim: ``d``.
        position_dims: indices of the position components.
        F: ``dt -> (d, d)`` for a linear model (``f(x, dt) = F(dt) x``), else ``None``.
        name: a short description.
    """

    f: Callable[[Array, Array], Array]
    Q: Callable[[Array], Array]
    dim: int
    position_dims: tuple[int, ...]
    F: Callable[[Array], Array] | None = None
    name: str = ""

    def jacobian(self, x: Array, dt: ArrayLike) -> Array:
        """``(d, d)`` ``df/dx`` at ``x`` (exact ``F(dt)`` for a linear model)."""
        if self.F is not None:
            return self.F(jnp.asarray(dt, jnp.result_type(x)))
        return jax.jacfwd(self.f)(x, dt)


class MeasurementModel(NamedTuple):
    """``z = h(x) + w``, ``w ~ N(0, R)`` (or a mixture, see :func:`glint_mixture`).

    Attributes:
        h: ``x (d,) -> (m,)``, traceable.
        R: ``(m, m)`` measurement-noise covariance.
        angle_dims: measurement components that are angles (radians): innovations are wrapped to
            ``[-pi, pi)`` and sigma-point means are taken on the circle.
        H: ``(m, d)`` for a linear model, else ``None``.
        name: a short description.
    """

    h: Callable[[Array], Array]
    R: Array
    angle_dims: tuple[int, ...] = ()
    H: Array | None = None
    name: str = ""

    @property
    def dim(self) -> int:
        return int(np.shape(self.R)[-1])

    def jacobian(self, x: Array) -> Array:
        """``(m, d)`` ``dh/dx`` at ``x``."""
        if self.H is not None:
            return jnp.asarray(self.H, jnp.result_type(x))
        return jax.jacfwd(self.h)(x)


# ---------------------------------------------------------------------------------------------
# helpers


def _per_axis(q: ArrayLike, ndim: int, name: str) -> np.ndarray:
    if isinstance(ndim, bool) or not isinstance(ndim, int) or ndim < 1:
        raise ValueError(f"ndim: must be a positive int, got {ndim!r}")
    q = np.broadcast_to(np.asarray(q, float), (ndim,)) if np.ndim(q) <= 1 else np.asarray(q)
    if q.shape != (ndim,):
        raise ValueError(f"{name}: expected a scalar or one value per axis ({ndim},), got shape {q.shape}")
    if not np.all(np.isfinite(q)) or np.any(q <= 0):
        raise ValueError(f"{name}: must be finite and > 0, got {q.tolist()}")
    return q


def _block_diag(blocks: Sequence[Array]) -> Array:
    return jax.scipy.linalg.block_diag(*blocks)


def _fdt(dt) -> Array:
    """``dt`` as a floating JAX scalar (ints become the default float type)."""
    dt = jnp.asarray(dt)
    return dt if jnp.issubdtype(dt.dtype, jnp.floating) else dt.astype(jnp.zeros(()).dtype)


# ---------------------------------------------------------------------------------------------
# motion models


def _nth_F(order: int, dt: Array) -> Array:
    n = order + 1
    i = np.arange(n)[:, None]
    j = np.arange(n)[None, :]
    power = np.maximum(j - i, 0)
    coef = np.where(j >= i, 1.0 / np.vectorize(math.factorial)(power), 0.0)
    return jnp.asarray(coef, dt.dtype) * dt ** jnp.asarray(power, dt.dtype)


def _nth_Q(order: int, dt: Array) -> Array:
    """Unit-diffusion ``Q(dt)`` of the N-times integrated white noise (Stone Soup's formula)."""
    n = order + 1
    i = np.arange(n)[:, None]
    j = np.arange(n)[None, :]
    fact = np.vectorize(math.factorial)
    power = 2 * order + 1 - i - j
    coef = 1.0 / (fact(order - i) * fact(order - j) * power)
    return jnp.asarray(coef, dt.dtype) * jnp.abs(dt) ** jnp.asarray(power, dt.dtype)


def nth_derivative(order: int, ndim: int = 1, q: ArrayLike = 1.0) -> MotionModel:
    """The ``order``-th derivative is (nearly) constant on every one of ``ndim`` axes.

    State per axis ``[p, p', ..., p^(order)]`` (``order + 1`` entries), axes stacked. Stone Soup's
    ``ConstantNthDerivative`` per axis combined with ``CombinedLinearGaussianTransitionModel``.

    Args:
        order: ``N >= 1`` (1: constant velocity, 2: constant acceleration).
        ndim: spatial dimension.
        q: diffusion coefficient, a scalar or one per axis.
    """
    if isinstance(order, bool) or not isinstance(order, int) or order < 1:
        raise ValueError(f"order: must be an int >= 1, got {order!r}")
    qs = _per_axis(q, ndim, "q")
    n = order + 1

    def F(dt):
        dt = _fdt(dt)
        return _block_diag([_nth_F(order, dt)] * ndim)

    def Q(dt):
        dt = _fdt(dt)
        return _block_diag([float(qa) * _nth_Q(order, dt) for qa in qs])

    def f(x, dt):
        return F(jnp.asarray(dt, x.dtype)) @ x

    names = {1: "constant velocity", 2: "constant acceleration"}
    return MotionModel(
        f,
        Q,
        n * ndim,
        tuple(range(0, n * ndim, n)),
        F,
        f"{names.get(order, f'constant derivative {order}')} ({ndim}-D)",
    )


def constant_velocity(ndim: int = 2, q: ArrayLike = 1.0) -> MotionModel:
    """Nearly constant velocity, state ``[x, vx, y, vy, ...]``; ``Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]``
    per axis (Stone Soup's ``ConstantVelocity``)."""
    return nth_derivative(1, ndim, q)


def constant_acceleration(ndim: int = 2, q: ArrayLike = 1.0) -> MotionModel:
    """Nearly constant acceleration, state ``[x, vx, ax, y, vy, ay, ...]`` (``ConstantAcceleration``)."""
    return nth_derivative(2, ndim, q)


def random_walk(ndim: int = 1, q: ArrayLike = 1.0) -> MotionModel:
    """``x_k = x_{k-1} + v``, ``Q = q dt I`` (Stone Soup's ``RandomWalk`` per axis)."""
    qs = _per_axis(q, ndim, "q")

    def F(dt):
        return jnp.eye(ndim, dtype=_fdt(dt).dtype)

    def Q(dt):
        dt = _fdt(dt)
        return jnp.diag(jnp.asarray(qs, dt.dtype)) * jnp.abs(dt)

    return MotionModel(lambda x, dt: x, Q, ndim, tuple(range(ndim)), F, f"random walk ({ndim}-D)")


def _singer_F(alpha: float, dt: Array) -> Array:
    e = jnp.exp(-alpha * dt)
    one, zero = jnp.ones_like(dt), jnp.zeros_like(dt)
    return jnp.stack(
        [
            jnp.stack([one, dt, (alpha * dt - 1 + e) / alpha**2]),
            jnp.stack([zero, one, (1 - e) / alpha]),
            jnp.stack([zero, zero, e]),
        ]
    )


def _singer_Q(alpha: float, dt: Array) -> Array:
    """Closed-form Singer ``Q(dt)`` for unit diffusion (Stone Soup's ``Singer`` docstring)."""
    a, t = alpha, jnp.abs(dt)
    e1, e2 = jnp.exp(-a * t), jnp.exp(-2 * a * t)
    q11 = ((1 - e2) + 2 * a * t + 2 * a**3 * t**3 / 3 - 2 * a**2 * t**2 - 4 * a * t * e1) / (2 * a**5)
    q12 = (a * t - (1 - e1)) ** 2 / (2 * a**4)
    q13 = ((1 - e2) - 2 * a * t * e1) / (2 * a**3)
    q22 = (2 * a * t - 4 * (1 - e1) + (1 - e2)) / (2 * a**3)
    q23 = (1 - e1) ** 2 / (2 * a**2)
    q33 = (1 - e2) / (2 * a)
    return jnp.stack([jnp.stack([q11, q12, q13]), jnp.stack([q12, q22, q23]), jnp.stack([q13, q23, q33])])


def singer(ndim: int = 1, q: ArrayLike = 1.0, alpha: float = 0.1) -> MotionModel:
    """Singer model per axis, state ``[p, v, a]``: ``da = -alpha a dt + dW`` (Singer 1970).

    Args:
        ndim: spatial dimension.
        q: acceleration diffusion coefficient (scalar or per axis).
        alpha: damping, the reciprocal of the manoeuvre time constant (> 0).
    """
    qs = _per_axis(q, ndim, "q")
    if not (np.isfinite(alpha) and alpha > 0):
        raise ValueError(f"alpha: must be finite and > 0, got {alpha!r}")
    alpha = float(alpha)

    def F(dt):
        dt = _fdt(dt)
        return _block_diag([_singer_F(alpha, dt)] * ndim)

    def Q(dt):
        dt = _fdt(dt)
        return _block_diag([float(qa) * _singer_Q(alpha, dt) for qa in qs])

    return MotionModel(
        lambda x, dt: F(jnp.asarray(dt, x.dtype)) @ x,
        Q,
        3 * ndim,
        tuple(range(0, 3 * ndim, 3)),
        F,
        f"Singer ({ndim}-D, alpha={alpha})",
    )


def _turn_F(omega: Array, dt: Array) -> Array:
    """``[x, vx, y, vy]`` transition for turn rate ``omega`` (Stone Soup's ``KnownTurnRate``)."""
    w = jnp.where(jnp.abs(omega) < 1e-12, 1e-12, omega)
    s, c = jnp.sin(w * dt), jnp.cos(w * dt)
    zero, one = jnp.zeros_like(s), jnp.ones_like(s)
    return jnp.stack(
        [
            jnp.stack([one, s / w, zero, (c - 1) / w]),
            jnp.stack([zero, c, zero, -s]),
            jnp.stack([zero, (1 - c) / w, one, s / w]),
            jnp.stack([zero, s, zero, c]),
        ]
    )


def coordinated_turn(omega: float, q: ArrayLike = 1.0) -> MotionModel:
    """Coordinated turn at a known rate ``omega`` (rad/s), state ``[x, vx, y, vy]``.

    ``Q`` is the constant-velocity ``Q`` per axis with coefficients ``q = (q_x, q_y)``, as Stone
    Soup's ``KnownTurnRate(turn_noise_diff_coeffs, turn_rate)``.
    """
    qs = _per_axis(q, 2, "q")
    omega = float(omega)
    if not np.isfinite(omega):
        raise ValueError(f"omega: must be finite, got {omega!r}")

    def F(dt):
        dt = _fdt(dt)
        return _turn_F(jnp.asarray(omega, dt.dtype), dt)

    def Q(dt):
        dt = _fdt(dt)
        return _block_diag([float(qa) * _nth_Q(1, dt) for qa in qs])

    return MotionModel(
        lambda x, dt: F(jnp.asarray(dt, x.dtype)) @ x, Q, 4, (0, 2), F, f"coordinated turn (omega={omega})"
    )


def coordinated_turn_unknown_rate(q: ArrayLike = 1.0, q_turn: float = 1e-4) -> MotionModel:
    """Coordinated turn with the rate as a state, ``[x, vx, y, vy, omega]`` (Stone Soup's
    ``ConstantTurn(linear_noise_coeffs=q, turn_noise_coeff=q_turn)``); nonlinear in ``omega``.

    ``Q = blockdiag(q_x Q_cv(dt), q_y Q_cv(dt), q_turn dt)``.
    """
    qs = _per_axis(q, 2, "q")
    if not (np.isfinite(q_turn) and q_turn > 0):
        raise ValueError(f"q_turn: must be finite and > 0, got {q_turn!r}")

    def f(x, dt):
        dt = jnp.asarray(dt, x.dtype)
        pos = _turn_F(x[4], dt) @ x[:4]
        return jnp.concatenate([pos, x[4:5]])

    def Q(dt):
        dt = _fdt(dt)
        return _block_diag(
            [float(qs[0]) * _nth_Q(1, dt), float(qs[1]) * _nth_Q(1, dt), (q_turn * jnp.abs(dt)).reshape(1, 1)]
        )

    return MotionModel(f, Q, 5, (0, 2), None, "coordinated turn, unknown rate")


# ---------------------------------------------------------------------------------------------
# measurement models


def _check_cov(R: ArrayLike, m: int, name: str = "R") -> jnp.ndarray:
    R = np.asarray(R, float)
    if R.ndim == 0:
        R = R * np.eye(m)
    elif R.ndim == 1:
        if R.shape != (m,):
            raise ValueError(
                f"{name}: expected {m} standard deviations or an ({m}, {m}) covariance, got shape {R.shape}"
            )
        R = np.diag(R**2)
    if R.shape != (m, m):
        raise ValueError(f"{name}: expected shape ({m}, {m}), got {R.shape}")
    if not np.all(np.isfinite(R)) or np.linalg.eigvalsh(0.5 * (R + R.T))[0] <= 0:
        raise ValueError(f"{name}: must be a finite positive definite covariance")
    return jnp.asarray(R)


def _check_dims(dims: Sequence[int], n: int, name: str) -> tuple[int, ...]:
    dims = tuple(int(i) for i in dims)
    if len(dims) != n or len(set(dims)) != n or min(dims) < 0:
        raise ValueError(f"{name}: expected {n} distinct non-negative state indices, got {dims}")
    return dims


def cartesian_position(position_dims: Sequence[int], state_dim: int, R: ArrayLike = 1.0) -> MeasurementModel:
    """``z = H x + w`` picking ``position_dims`` out of a ``state_dim`` state (``LinearGaussian``).

    ``R``: a scalar variance, per-component standard deviations, or a covariance.
    """
    dims = tuple(int(i) for i in position_dims)
    if not dims or max(dims) >= state_dim or min(dims) < 0:
        raise ValueError(f"position_dims: indices must lie in [0, {state_dim}), got {dims}")
    H = np.zeros((len(dims), state_dim))
    H[np.arange(len(dims)), dims] = 1.0
    Hj = jnp.asarray(H)
    return MeasurementModel(
        lambda x: Hj.astype(x.dtype) @ x, _check_cov(R, len(dims)), (), Hj, "cartesian position"
    )


def bearing_range(
    position_dims: Sequence[int] = (0, 2), R: ArrayLike = (0.01, 1.0), sensor: ArrayLike = (0.0, 0.0)
) -> MeasurementModel:
    """``z = [atan2(y - s_y, x - s_x), |p - s|]`` (Stone Soup's ``CartesianToBearingRange``).

    ``R`` as in :func:`cartesian_position` (default std 0.01 rad, 1 m); the bearing is an angle.
    """
    dims = _check_dims(position_dims, 2, "position_dims")
    s = jnp.asarray(sensor, float)

    def h(x):
        dx, dy = x[dims[0]] - s[0].astype(x.dtype), x[dims[1]] - s[1].astype(x.dtype)
        return jnp.stack([jnp.arctan2(dy, dx), jnp.sqrt(dx * dx + dy * dy)])

    return MeasurementModel(h, _check_cov(R, 2), (0,), None, "bearing-range")


def elevation_bearing_range(
    position_dims: Sequence[int] = (0, 2, 4),
    R: ArrayLike = (0.01, 0.01, 1.0),
    sensor: ArrayLike = (0.0, 0.0, 0.0),
) -> MeasurementModel:
    """``z = [elevation, bearing, range]`` (Stone Soup's ``CartesianToElevationBearingRange``);
    elevation and bearing are angles."""
    dims = _check_dims(position_dims, 3, "position_dims")
    s = jnp.asarray(sensor, float)

    def h(x):
        d = jnp.stack([x[i] for i in dims]) - s.astype(x.dtype)
        rho_xy = jnp.sqrt(d[0] ** 2 + d[1] ** 2)
        return jnp.stack([jnp.arctan2(d[2], rho_xy), jnp.arctan2(d[1], d[0]), jnp.sqrt(jnp.sum(d * d))])

    return MeasurementModel(h, _check_cov(R, 3), (0, 1), None, "elevation-bearing-range")


def bearings_only(
    position_dims: Sequence[int] = (0, 2), R: ArrayLike = 0.01**2, sensor: ArrayLike = (0.0, 0.0)
) -> MeasurementModel:
    """``z = atan2(y - s_y, x - s_x)`` (Stone Soup's ``Cartesian2DToBearing``); an angle."""
    dims = _check_dims(position_dims, 2, "position_dims")
    s = jnp.asarray(sensor, float)

    def h(x):
        return jnp.arctan2(x[dims[1]] - s[1].astype(x.dtype), x[dims[0]] - s[0].astype(x.dtype))[None]

    return MeasurementModel(h, _check_cov(R, 1), (0,), None, "bearings only")


def bearing_range_rate(
    position_dims: Sequence[int] = (0, 2),
    velocity_dims: Sequence[int] = (1, 3),
    R: ArrayLike = (0.01, 1.0, 0.1),
    sensor: ArrayLike = (0.0, 0.0),
) -> MeasurementModel:
    """``z = [bearing, range, range rate]`` of a 2-D target from a static sensor (Stone Soup's
    ``CartesianToBearingRangeRate2D`` for a static sensor): ``range rate = (p - s) . v / |p - s|``."""
    pd = _check_dims(position_dims, 2, "position_dims")
    vd = _check_dims(velocity_dims, 2, "velocity_dims")
    s = jnp.asarray(sensor, float)

    def h(x):
        dx, dy = x[pd[0]] - s[0].astype(x.dtype), x[pd[1]] - s[1].astype(x.dtype)
        rho = jnp.sqrt(dx * dx + dy * dy)
        return jnp.stack([jnp.arctan2(dy, dx), rho, (dx * x[vd[0]] + dy * x[vd[1]]) / rho])

    return MeasurementModel(h, _check_cov(R, 3), (0,), None, "bearing-range-rate")


def glint_mixture(
    R: ArrayLike, frequency: float = 0.1, tail_scale: float = 10.0, dtype: Any = None
) -> GaussianMixture:
    """Two-component Gaussian mixture for glint noise: ``(1 - eps) N(0, R) + eps N(0, s^2 R)``.

    The wide component models the heavy glint tail (seed 000 §IV-D uses a Gaussian-Laplace glint
    mixture; the filters assume Gaussian mixtures of this kind).

    Args:
        R: ``(m, m)`` core covariance.
        frequency: ``eps`` in ``(0, 1)``.
        tail_scale: ``s > 1``, the tail's standard-deviation factor.
    """
    R = np.asarray(R, float)
    if R.ndim != 2 or R.shape[0] != R.shape[1]:
        raise ValueError(f"R: expected a square covariance, got shape {R.shape}")
    if not 0.0 < frequency < 1.0:
        raise ValueError(f"frequency: must lie in (0, 1), got {frequency!r}")
    if not tail_scale > 0:
        raise ValueError(f"tail_scale: must be > 0, got {tail_scale!r}")
    m = R.shape[0]
    return GaussianMixture.create(
        [1 - frequency, frequency], np.zeros((2, m)), np.stack([R, tail_scale**2 * R]), dtype=dtype
    )


# ---------------------------------------------------------------------------------------------
# assembling a StateSpaceModel


def noise_scaler(Q: Callable[[Array], Array], dt_ref: float) -> Callable[[GaussianMixture, Array], Any]:
    """``(noise, dt) -> noise'``: map a process-noise mixture given at ``dt_ref`` to the step ``dt``.

    Every component goes through the linear map ``A(dt) = chol(Q(dt)) chol(Q(dt_ref))^-1`` (means
    ``A m``, covariances ``A P A^T``), so a single Gaussian ``N(0, Q(dt_ref))`` becomes exactly
    ``N(0, Q(dt))``, a mixture keeps its shape, and the map is linear in the noise parameters (they
    stay differentiable leaves of ``params``).
    """

    def scale(noise, dt: Array):
        if not isinstance(noise, GaussianMixture):  # a (mean, cov) pair of a single-Gaussian filter
            mean, cov = noise
            A = _map(jnp.asarray(mean).dtype, dt)
            pair = (A @ mean, A @ cov @ A.T)
            return type(noise)(*pair) if hasattr(noise, "_fields") else pair
        A = _map(noise.means.dtype, dt)
        means = noise.means @ A.T
        covs = jnp.einsum("ij,kjl,ml->kim", A, noise.covs, A)
        eye = jnp.broadcast_to(jnp.eye(A.shape[0], dtype=A.dtype), covs.shape)
        covs = jnp.where(noise.mask[:, None, None], covs, eye)
        return GaussianMixture(noise.weights, jnp.where(noise.mask[:, None], means, 0), covs, noise.mask)

    def _map(dtype, dt):
        L_ref = jnp.linalg.cholesky(Q(jnp.asarray(dt_ref, dtype)))
        L_dt = jnp.linalg.cholesky(Q(jnp.asarray(dt, dtype)))
        d = L_ref.shape[0]
        return L_dt @ jax.scipy.linalg.solve_triangular(L_ref, jnp.eye(d, dtype=dtype), lower=True)

    return scale


def state_space_model(
    motion: MotionModel,
    measurement: MeasurementModel,
    prior: GaussianMixture,
    *,
    dt: float = 1.0,
    process_noise: GaussianMixture | None = None,
    measurement_noise: GaussianMixture | None = None,
) -> Any:
    """A :class:`~gmjax.models.StateSpaceModel` from a motion and a measurement model.

    ``f(x, inputs)`` propagates over ``inputs.dt`` (``dt`` when the step carries none) and the
    process noise is scaled to that ``dt`` at every step (:func:`noise_scaler`); measurement angles
    are declared (``angle_dims``).

    Args:
        motion, measurement: library models (or your own of the same types).
        prior: GM of ``x_0``.
        dt: the default step length, and the one ``process_noise`` is given at.
        process_noise: GM process noise at ``dt`` (default ``N(0, motion.Q(dt))``).
        measurement_noise: GM measurement noise (default ``N(0, measurement.R)``; e.g.
            :func:`glint_mixture`).
    """
    from gmjax.models.base import StateSpaceModel

    dtype = prior.means.dtype
    d, m = motion.dim, measurement.dim
    if prior.dim != d:
        raise ValueError(f"prior: dimension {prior.dim} does not match the motion model's {d}")
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt: must be finite and > 0, got {dt!r}")
    if process_noise is None:
        process_noise = GaussianMixture.create(
            [1.0], np.zeros((1, d)), np.asarray(motion.Q(jnp.asarray(dt, dtype)))[None], dtype=dtype
        )
    if measurement_noise is None:
        measurement_noise = GaussianMixture.create(
            [1.0], np.zeros((1, m)), np.asarray(measurement.R)[None], dtype=dtype
        )
    if process_noise.dim != d:
        raise ValueError(f"process_noise: dimension {process_noise.dim} does not match the state's {d}")
    if measurement_noise.dim != m:
        raise ValueError(
            f"measurement_noise: dimension {measurement_noise.dim} does not match the measurement's {m}"
        )
    default_dt = float(dt)
    scale = noise_scaler(motion.Q, default_dt)

    def step_dt(inputs, dtype):
        return jnp.asarray(default_dt if inputs.dt is None else inputs.dt, dtype)

    def f(x, inputs):
        return motion.f(x, step_dt(inputs, x.dtype))

    def h(x, inputs):
        return measurement.h(x)

    def noise_at(noise, inputs):
        if inputs.dt is None:
            return noise
        return scale(noise, inputs.dt)

    F_of_dt = motion.F
    f_jac = None if F_of_dt is None else (lambda x, inputs: F_of_dt(step_dt(inputs, x.dtype)))
    h_jac = None if measurement.H is None else (lambda x, inputs: jnp.asarray(measurement.H, x.dtype))
    return StateSpaceModel(
        f=f,
        h=h,
        process_noise=process_noise,
        measurement_noise=measurement_noise,
        prior=prior,
        f_jacobian=f_jac,
        h_jacobian=h_jac,
        angle_dims=measurement.angle_dims,
        process_noise_at=noise_at,
        call="inputs",
    )
