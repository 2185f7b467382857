"""Multi-target scenarios and their simulation: births, deaths, detections with ``P_D``, Poisson clutter.

A :class:`MultiTargetScenario` holds the single-target model the filter assumes (a
:class:`~gmjax.models.StateSpaceModel`), the multi-target settings (birth intensity, ``P_S``, ``P_D``,
clutter rate, the surveillance region in measurement space) and a truth schedule: target ``i`` is
born at step ``birth_times[i]`` in state ``initial_states[i]``, moves with ``f`` (plus process noise
scaled by ``truth_noise_scale``; 0 by default, straight deterministic tracks as in Vo & Ma's figures)
and dies at step ``death_times[i]`` (alive for ``birth <= k < death``, steps ``k = 1 .. T``).

:func:`simulate` draws one run (``vmap`` it over keys for a Monte Carlo study): every live target is
detected with probability ``P_D`` (``z = h(x) + w``); ``Poisson(lambda_c)`` clutter points are uniform
over the region. Each scan is a padded set ``(M, m)`` with NaN rows for absent measurements
(the convention of :mod:`gmjax.multitarget.phd`), detections first; when a scan holds more than ``M``
measurements the last clutter points are dropped **and** ``overflow`` is set for that step.

**Capacities in buckets.** ``M`` is a static shape: a filter compiled for one ``M`` is compiled again
for another. :func:`bucket_capacity` rounds a size up to a power of two and :func:`clutter_capacity`
picks the bucket that holds a scan of ``Poisson(lambda_c)`` clutter plus every target except with
probability ``overflow_prob``, so a study whose clutter rate varies from run to run (``simulate``'s
``clutter_rate``, traced) compiles one program per bucket, a handful, not one per rate; a scan that
still overflows is flagged, as always.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import gaussian
from gmjax._types import Array, ArrayLike, PRNGKey
from gmjax.filters.local import gaussian_moments
from gmjax.mixture import GaussianMixture, from_gaussian
from gmjax.models.base import StateSpaceModel

__all__ = [
    "bucket_capacity",
    "clutter_capacity",
    "MultiTargetScenario",
    "MultiTargetSample",
    "simulate",
    "vo_ma_linear",
    "crossing_targets",
    "range_bearing",
    "cv_model",
]


def bucket_capacity(n: int, *, minimum: int = 8) -> int:
    """The measurement capacity for scans of up to ``n`` rows: the smallest power of two that is at
    least ``max(n, minimum)`` (so sizes 9..16 share 16, 17..32 share 32, ...).

    Raises:
        ValueError: ``n`` negative or ``minimum`` below 1.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"n: expected a non-negative int, got {n!r}")
    if isinstance(minimum, bool) or not isinstance(minimum, (int, np.integer)) or minimum < 1:
        raise ValueError(f"minimum: expected a positive int, got {minimum!r}")
    return 1 << (max(int(n), int(minimum)) - 1).bit_length()


def clutter_capacity(
    clutter_rate: float, n_targets: int, *, overflow_prob: float = 1e-6, minimum: int = 8
) -> int:
    """The :func:`bucket_capacity` of a scan with every one of ``n_targets`` detected and
    ``Poisson(clutter_rate)`` clutter points, exceeded with probability at most ``overflow_prob``
    (the Poisson quantile ``1 - overflow_prob``; a scan that still overflows is flagged by
    :func:`simulate`).

    Raises:
        ValueError: a negative or non-finite rate, a negative target count, ``overflow_prob`` outside
            ``(0, 1)``.
    """
    from scipy.stats import poisson

    rate = float(clutter_rate)
    if not math.isfinite(rate) or rate < 0:
        raise ValueError(f"clutter_rate: expected a finite rate >= 0, got {clutter_rate!r}")
    if isinstance(n_targets, bool) or not isinstance(n_targets, (int, np.integer)) or n_targets < 0:
        raise ValueError(f"n_targets: expected a non-negative int, got {n_targets!r}")
    if not 0.0 < float(overflow_prob) < 1.0:
        raise ValueError(f"overflow_prob: expected a probability in (0, 1), got {overflow_prob!r}")
    clutter = 0 if rate == 0 else int(poisson.ppf(1.0 - float(overflow_prob), rate))
    return bucket_capacity(int(n_targets) + clutter, minimum=minimum)


class MultiTargetScenario(NamedTuple):
    """A multi-target tracking scenario (see the module docstring).

    Attributes:
        name: short identifier.
        model: the single-target :class:`StateSpaceModel` (``f``, ``h``, noises; its prior is unused).
        n_steps: ``T``.
        birth: birth intensity (GM, weights = expected births per step).
        survival_prob, detection_prob: ``P_S``, ``P_D``.
        clutter_rate: ``lambda_c``, mean clutter returns per scan.
        region: ``(lo (m,), hi (m,))``, the box in measurement space where clutter is uniform.
        initial_states: ``(N, d)`` each target's state at its birth step.
        birth_times, death_times: ``(N,)`` ints; target ``i`` is alive at steps ``birth <= k < death``.
        max_measurements: ``M``, the capacity of a scan.
        truth_noise_scale: factor on the process noise driving the true tracks (0: deterministic).
        position_dims: state indices of the position (for OSPA/GOSPA).
        description: what was taken from the paper and what we chose.
    """

    name: str
    model: StateSpaceModel
    n_steps: int
    birth: GaussianMixture
    survival_prob: float
    detection_prob: float
    clutter_rate: float
    region: tuple[Array, Array]
    initial_states: Array
    birth_times: Array
    death_times: Array
    max_measurements: int
    truth_noise_scale: float = 0.0
    position_dims: tuple[int, ...] = (0, 1)
    description: str = ""

    @property
    def clutter_density(self) -> float:
        """``1 / V``, the uniform clutter density over :attr:`region`."""
        lo, hi = (np.asarray(a, float) for a in self.region)
        return float(1.0 / np.prod(hi - lo))

    @property
    def n_targets(self) -> int:
        return int(np.asarray(self.initial_states).shape[0])

    def filter_kwargs(self) -> dict:
        """The multi-target keyword arguments of :func:`gmjax.multitarget.gm_phd` for this scenario."""
        return dict(
            birth=self.birth,
            survival_prob=self.survival_prob,
            detection_prob=self.detection_prob,
            clutter_rate=self.clutter_rate,
            clutter_density=self.clutter_density,
        )


class MultiTargetSample(NamedTuple):
    """One simulated run (leading axis ``T``; add a run axis with ``vmap``).

    Attributes:
        states: ``(T, N, d)`` true states (0 where not alive).
        alive: ``(T, N)`` bool.
        zs: ``(T, M, m)`` padded scans, NaN rows absent, detections first.
        detected: ``(T, N)`` bool, which targets were detected (and kept).
        n_clutter: ``(T,)`` int32, clutter points drawn (before any overflow).
        overflow: ``(T,)`` bool, the scan held more than ``M`` measurements (clutter was dropped).
    """

    states: Array
    alive: Array
    zs: Array
    detected: Array
    n_clutter: Array
    overflow: Array


def simulate(
    scenario: MultiTargetScenario, key: PRNGKey, *, clutter_rate: ArrayLike | None = None
) -> MultiTargetSample:
    """Simulate one run of ``scenario`` (traceable: ``jax.vmap(simulate, (None, 0))`` over keys).

    ``clutter_rate`` (traced; default ``scenario.clutter_rate``) replaces the scenario's rate, so runs
    with their own rates ``vmap`` in one program: ``jax.vmap(lambda k, c: simulate(sc, k,
    clutter_rate=c))(keys, rates)`` (pick ``scenario.max_measurements`` with :func:`clutter_capacity`).
    """
    model = scenario.model
    x_init = jnp.asarray(scenario.initial_states)
    dtype = x_init.dtype
    N, d = x_init.shape
    M = int(scenario.max_measurements)
    T = int(scenario.n_steps)
    q_mean, q_cov = gaussian_moments(model.process_noise)
    r_mean, r_cov = gaussian_moments(model.measurement_noise)
    # singular process noises are common (the white-noise acceleration Q has rank 2): repaired factor
    Lq = gaussian.safe_cholesky(q_cov.astype(dtype)).factor * scenario.truth_noise_scale
    Lr = gaussian.safe_cholesky(r_cov.astype(dtype)).factor
    m = r_cov.shape[-1]
    lo, hi = (jnp.asarray(a, dtype) for a in scenario.region)
    births = jnp.asarray(scenario.birth_times, jnp.int32)
    deaths = jnp.asarray(scenario.death_times, jnp.int32)
    f = jax.vmap(model.f, in_axes=(0, None))
    h = jax.vmap(model.h, in_axes=(0, None))
    p_d = jnp.asarray(scenario.detection_prob, dtype)
    rate = jnp.asarray(scenario.clutter_rate if clutter_rate is None else clutter_rate, dtype)

    def step(x, inp):
        t, k = inp
        kq, kd, kr, kn, kc = jax.random.split(k, 5)
        v = jax.random.normal(kq, (N, d), dtype) @ Lq.T + (q_mean * (scenario.truth_noise_scale > 0))
        x = jnp.where((t == births)[:, None], x_init, f(x, t) + v)
        alive = (births <= t) & (t < deaths)
        detected = alive & (jax.random.uniform(kd, (N,), dtype) < p_d)
        z_t = h(x, t) + r_mean + jax.random.normal(kr, (N, m), dtype) @ Lr.T
        n_c = jax.random.poisson(kn, rate).astype(jnp.int32)
        z_c = lo + (hi - lo) * jax.random.uniform(kc, (M, m), dtype)
        cand = jnp.concatenate([z_t, z_c])
        valid = jnp.concatenate([detected, jnp.arange(M) < n_c])
        order = jnp.argsort(~valid, stable=True)[:M]
        kept = valid[order]
        zs = jnp.where(kept[:, None], cand[order], jnp.nan)
        n_valid = jnp.sum(valid.astype(jnp.int32))
        x_out = jnp.where(alive[:, None], x, 0.0)
        return x, (x_out, alive, zs, detected, n_c, n_valid > M)

    ts = jnp.arange(1, T + 1, dtype=jnp.int32)
    _, out = jax.lax.scan(step, x_init, (ts, jax.random.split(key, T)))
    return MultiTargetSample(*out)


# ----------------------------------------------------------------------------- models


def cv_model(
    sigma_v: float, measurement: Any, R: ArrayLike, *, dt: float = 1.0, dtype: Any = None
) -> StateSpaceModel:
    """2-D constant velocity, state ``[p_x, p_y, v_x, v_y]``, with the discrete white-noise acceleration
    ``Q = sigma_v^2 [[dt^4/4 I, dt^3/2 I], [dt^3/2 I, dt^2 I]]`` (Vo & Ma 2006, §VI).

    Args:
        sigma_v: acceleration noise standard deviation.
        measurement: ``h(x (4,), t) -> (m,)`` or ``"position"`` (``H = [I, 0]``).
        R: ``(m, m)`` measurement noise covariance.
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    I2 = np.eye(2)
    F = np.block([[I2, dt * I2], [np.zeros((2, 2)), I2]])
    Q = sigma_v**2 * np.block([[dt**4 / 4 * I2, dt**3 / 2 * I2], [dt**3 / 2 * I2, dt**2 * I2]])
    Fj = jnp.asarray(F, dtype)
    if measurement == "position":
        Hj = jnp.asarray(np.hstack([I2, np.zeros((2, 2))]), dtype)

        def h(x, t):
            return Hj @ x

        h_jac = lambda x, t: Hj  # noqa: E731
    else:
        h, h_jac = measurement, None
    R = jnp.asarray(R, dtype)
    return StateSpaceModel(
        f=lambda x, t: Fj @ x,
        h=h,
        process_noise=from_gaussian(jnp.zeros(4, dtype), jnp.asarray(Q, dtype)),
        measurement_noise=from_gaussian(jnp.zeros(R.shape[0], dtype), R),
        prior=from_gaussian(jnp.zeros(4, dtype), jnp.eye(4, dtype=dtype)),
        f_jacobian=lambda x, t: Fj,
        h_jacobian=h_jac,
    )


def _birth(means, cov, weight, dtype) -> GaussianMixture:
    means = jnp.asarray(means, dtype)
    J = means.shape[0]
    return GaussianMixture(
        jnp.full(J, weight, dtype),
        means,
        jnp.broadcast_to(jnp.asarray(cov, dtype), (J, 4, 4)),
        jnp.ones(J, bool),
    )


def vo_ma_linear(
    *,
    clutter_rate: float = 10.0,
    n_steps: int = 100,
    max_measurements: int = 32,
    detection_prob: float = 0.98,
    survival_prob: float = 0.99,
    dtype: Any = None,
) -> MultiTargetScenario:
    """The linear scenario of Vo & Ma 2006, §VI-A (Example 1), without spawning.

    From the paper: 2-D CV targets, ``T = 1 s``, ``sigma_v = 5 m/s^2``, position measurements with
    ``sigma_eps = 10 m``, ``P_S = 0.99``, ``P_D = 0.98``, region ``[-1000, 1000]^2`` m, births
    ``gamma = 0.1 N(m1, P) + 0.1 N(m2, P)`` with ``m1 = [250, 250, 0, 0]``, ``m2 = [-250, -250, 0, 0]``,
    ``P = diag(100, 100, 25, 25)``. Ours: clutter rate 10 per scan by default (the paper: ``12.5e-6
    m^-2``, i.e. 50 per scan; pass ``clutter_rate=50`` and a larger ``max_measurements``), no spawned
    target, and four deterministic tracks born at the two birth sites (steps 1, 1, 20, 40; two die at
    steps 70 and 85), a scan capacity ``M = 32``.
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    model = cv_model(5.0, "position", 100.0 * np.eye(2), dtype=dtype)
    birth = _birth(
        [[250.0, 250.0, 0.0, 0.0], [-250.0, -250.0, 0.0, 0.0]],
        np.diag([100.0, 100.0, 25.0, 25.0]),
        0.1,
        dtype,
    )
    x0 = np.array(
        [
            [250.0, 250.0, 2.5, -11.5],
            [-250.0, -250.0, 11.5, -2.5],
            [250.0, 250.0, -10.0, 2.0],
            [-250.0, -250.0, -5.0, 8.0],
        ]
    )
    return MultiTargetScenario(
        name="vo_ma_linear",
        model=model,
        n_steps=int(n_steps),
        birth=birth,
        survival_prob=survival_prob,
        detection_prob=detection_prob,
        clutter_rate=clutter_rate,
        region=(jnp.full(2, -1000.0, dtype), jnp.full(2, 1000.0, dtype)),
        initial_states=jnp.asarray(x0, dtype),
        birth_times=jnp.array([1, 1, 20, 40], jnp.int32),
        death_times=jnp.array([n_steps + 1, 70, n_steps + 1, 85], jnp.int32),
        max_measurements=int(max_measurements),
        description=vo_ma_linear.__doc__ or "",
    )


def crossing_targets(
    *,
    clutter_rate: float = 30.0,
    detection_prob: float = 0.9,
    n_steps: int = 100,
    max_measurements: int | None = None,
    dtype: Any = None,
) -> MultiTargetScenario:
    """Eight targets on straight tracks, three pairs crossing in the middle, in dense clutter.

    A harder companion of :func:`vo_ma_linear` (the PHD vs CPHD study of issue 47): more targets, staggered
    births and deaths, tracks that cross, more clutter and a lower ``P_D``. Every number is our choice.

    * Model: that of :func:`vo_ma_linear` (:func:`cv_model`, ``T = 1 s``, ``sigma_v = 5 m/s^2``, position
      measurements with ``sigma_eps = 10 m``), ``P_S = 0.99``, ``P_D = detection_prob`` (0.9), clutter
      ``Poisson(clutter_rate)`` (30) per scan uniform over the region ``[-1000, 1000]^2`` m.
    * Births: four sites at the corners ``A = (-600, -600)``, ``B = (600, -600)``, ``C = (-600, 600)``,
      ``D = (600, 600)``; the birth intensity ``sum_i 0.03 N([site_i, 0, 0], P)``,
      ``P = diag(100, 100, 400, 400)`` (position sd 10 m, velocity sd 20 m/s: the tracks' speeds are
      14-28 m/s), i.e. 0.12 expected births per step.
    * Truth: deterministic tracks (``truth_noise_scale = 0``), target ``i`` born at its site at step
      ``b_i`` with velocity ``v_i`` (m/s) and alive for ``b_i <= k < death_i``:

      ====  ====  =====  ================  =====
      i     site  b_i    v_i               death
      ====  ====  =====  ================  =====
      0     A     1      (15, 12.5)        80
      1     B     1      (-15, 12.5)       end
      2     C     10     (15, -12.5)       end
      3     D     20     (-20, -16.67)     85
      4     A     30     (15, 15)          end
      5     B     40     (-20, 20)         95
      6     C     50     (-2, -15)         end
      7     D     60     (-12, 0)          end
      ====  ====  =====  ================  =====

      ("end": ``n_steps + 1``, alive to the last step). The true count rises 2, 3, ..., 8 (steps
      60-79), then falls to 7, 6 and 5 (steps 95-100). Targets 0 and 1 cross at ``(0, -100)`` at step 41,
      2 and 3 at ``(0, 100)`` at step 50, 4 and 5 at ``(0, 0)`` at step 70 (the same point at the same
      step); every other pair of live targets stays at least 95 m apart. All tracks stay inside
      ``[-885, 885]^2`` over 100 steps.
    * Capacity: ``max_measurements`` defaults to ``clutter_capacity(clutter_rate, 8)`` (128 at the
      default rate): a scan overflows with probability below ``1e-6``.

    Raises:
        ValueError: a negative or non-finite ``clutter_rate``, ``detection_prob`` outside ``(0, 1]``,
            ``n_steps`` or ``max_measurements`` below 1.
    """
    rate = float(clutter_rate)
    if not math.isfinite(rate) or rate < 0:
        raise ValueError(f"clutter_rate: expected a finite rate >= 0, got {clutter_rate!r}")
    if not 0.0 < float(detection_prob) <= 1.0:
        raise ValueError(f"detection_prob: must lie in (0, 1], got {detection_prob!r}")
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 1:
        raise ValueError(f"n_steps: expected an int >= 1, got {n_steps!r}")
    if max_measurements is None:
        max_measurements = clutter_capacity(rate, 8)
    elif (
        isinstance(max_measurements, bool)
        or not isinstance(max_measurements, (int, np.integer))
        or max_measurements < 1
    ):
        raise ValueError(f"max_measurements: expected an int >= 1, got {max_measurements!r}")
    dtype = jnp.result_type(float) if dtype is None else dtype
    model = cv_model(5.0, "position", 100.0 * np.eye(2), dtype=dtype)
    sites = np.array([[-600.0, -600.0], [600.0, -600.0], [-600.0, 600.0], [600.0, 600.0]])  # A, B, C, D
    birth = _birth(np.hstack([sites, np.zeros((4, 2))]), np.diag([100.0, 100.0, 400.0, 400.0]), 0.03, dtype)
    site = [0, 1, 2, 3, 0, 1, 2, 3]
    births = [1, 1, 10, 20, 30, 40, 50, 60]
    # the three crossings: velocity = (crossing point - site) / (crossing step - birth step)
    velocities = np.array(
        [
            (np.array([0.0, -100.0]) - sites[0]) / 40,  # 0 meets 1 at (0, -100), step 41
            (np.array([0.0, -100.0]) - sites[1]) / 40,
            (np.array([0.0, 100.0]) - sites[2]) / 40,  # 2 meets 3 at (0, 100), step 50
            (np.array([0.0, 100.0]) - sites[3]) / 30,
            (np.array([0.0, 0.0]) - sites[0]) / 40,  # 4 meets 5 at (0, 0), step 70
            (np.array([0.0, 0.0]) - sites[1]) / 30,
            [-2.0, -15.0],
            [-12.0, 0.0],
        ]
    )
    x0 = np.hstack([sites[site], velocities])
    end = int(n_steps) + 1
    deaths = [80, end, end, 85, end, 95, end, end]
    return MultiTargetScenario(
        name="crossing_targets",
        model=model,
        n_steps=int(n_steps),
        birth=birth,
        survival_prob=0.99,
        detection_prob=float(detection_prob),
        clutter_rate=rate,
        region=(jnp.full(2, -1000.0, dtype), jnp.full(2, 1000.0, dtype)),
        initial_states=jnp.asarray(x0, dtype),
        birth_times=jnp.array(births, jnp.int32),
        death_times=jnp.array(deaths, jnp.int32),
        max_measurements=int(max_measurements),
        description=crossing_targets.__doc__ or "",
    )


def _range_bearing(x, t):
    del t
    px, py = x[0], x[1]
    sq = px * px + py * py
    r = jnp.sqrt(jnp.where(sq > 0, sq, 1.0))
    return jnp.stack([jnp.where(sq > 0, r, 0.0), jnp.arctan2(py, px)])


def range_bearing(
    *,
    clutter_rate: float = 10.0,
    n_steps: int = 60,
    max_measurements: int = 32,
    sigma_range: float = 5.0,
    sigma_bearing: float = 0.005,
    dtype: Any = None,
) -> MultiTargetScenario:
    """A range-bearing variant (EKF/UKF components): the Vo & Ma CV dynamics seen by a radar at the origin.

    Our choices: ``z = [range, bearing] + w``, ``sigma_r = 5 m``, ``sigma_theta = 0.005 rad``;
    clutter uniform over ``range in [0, 2000] m``, ``bearing in [-pi/2, pi/2]`` (the half plane
    ``x > 0`` the radar looks at; the targets stay there, so bearings are never wrapped);
    ``P_S = 0.99``, ``P_D = 0.98``; births ``0.1 N([500, 500, 0, 0], P) + 0.1 N([800, -300, 0, 0], P)``,
    ``P = diag(100, 100, 25, 25)``; three tracks (born at steps 1, 1, 15; one dies at step 45).
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    model = cv_model(5.0, _range_bearing, np.diag([sigma_range**2, sigma_bearing**2]), dtype=dtype)
    birth = _birth(
        [[500.0, 500.0, 0.0, 0.0], [800.0, -300.0, 0.0, 0.0]], np.diag([100.0, 100.0, 25.0, 25.0]), 0.1, dtype
    )
    x0 = np.array([[500.0, 500.0, 5.0, -8.0], [800.0, -300.0, -6.0, 6.0], [500.0, 500.0, 8.0, 3.0]])
    return MultiTargetScenario(
        name="range_bearing",
        model=model,
        n_steps=int(n_steps),
        birth=birth,
        survival_prob=0.99,
        detection_prob=0.98,
        clutter_rate=clutter_rate,
        region=(jnp.asarray([0.0, -math.pi / 2], dtype), jnp.asarray([2000.0, math.pi / 2], dtype)),
        initial_states=jnp.asarray(x0, dtype),
        birth_times=jnp.array([1, 1, 15], jnp.int32),
        death_times=jnp.array([n_steps + 1, 45, n_steps + 1], jnp.int32),
        max_measurements=int(max_measurements),
        description=range_bearing.__doc__ or "",
    )
