"""A user's own model, continued: angular Gaussian-mixture noise in the particle filter, the seed 004
bank with irregular dt, controls and per-step noise, and state-dependent process noise."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import filters
from gmjax import mixture as gmm
from gmjax.filters import StepInputs
from gmjax.mixture import GaussianMixture
from gmjax.models import StateSpaceModel
from gmjax.models import library as lib

jax.config.update("jax_enable_x64", True)


# --- the particle filter with a Gaussian-mixture noise whose means are angles ---------------------

T_PF = 25
P0_PF = np.diag([25.0, 1.0, 25.0, 1.0])
SIGMA_B, SIGMA_R = 0.02, 1.0


def _ambiguous_noise(bias: float, mirror: float) -> GaussianMixture:
    """Bearing-range noise: a biased core ``N((bias, 0), .)`` and a front/back ambiguity at bearing
    ``mirror`` (``pi`` or an equivalent angle) with weight 0.3."""
    cov = np.diag([SIGMA_B**2, SIGMA_R**2])
    return GaussianMixture.create([0.7, 0.3], [[bias, 0.0], [mirror, 0.0]], [cov, cov])


def _heading_model(noise: GaussianMixture) -> StateSpaceModel:
    """Constant velocity seen by a bearing-range sensor whose bearing is measured from a heading
    given per step in ``inputs.aux`` (so one compiled filter serves every heading)."""
    motion = lib.constant_velocity(2, 0.05)

    def h(x, inputs):
        return jnp.stack([jnp.arctan2(x[2], x[0]) - inputs.aux, jnp.hypot(x[0], x[2])])

    return StateSpaceModel(
        f=lambda x, inputs: motion.f(x, 1.0),
        h=h,
        process_noise=gmm.from_gaussian(jnp.zeros(4), motion.Q(jnp.asarray(1.0))),
        measurement_noise=noise,
        prior=gmm.from_gaussian(jnp.zeros(4), jnp.asarray(P0_PF)),
        angle_dims=(0,),
        call="inputs",
    )


def _pf_track():
    """A target passing behind the sensor (bearing crossing ±pi), its measurements drawn from
    :func:`_ambiguous_noise` in the heading-0 frame, and the raw (unwrapped) bearing noise."""
    rng = np.random.default_rng(3)
    p0, v = np.array([-100.0, 12.0]), np.array([0.4, -0.9])
    xs = np.stack([[p0[0] + v[0] * k, v[0], p0[1] + v[1] * k, v[1]] for k in range(1, T_PF + 1)])
    mirror = rng.uniform(size=T_PF) < 0.3
    wb = rng.normal(0, SIGMA_B, T_PF) + np.where(mirror, np.pi, 0.02)
    wr = rng.normal(0, SIGMA_R, T_PF)
    bearing = np.arctan2(xs[:, 2], xs[:, 0])
    x0 = xs[0] - np.array([0.4, 0.0, 0.0, 0.9]) + np.array([2.0, 0.2, -2.0, -0.1])
    return xs, x0, bearing + wb, np.hypot(xs[:, 0], xs[:, 2]) + wr


def _wrap(a):
    return np.mod(a + np.pi, 2 * np.pi) - np.pi


CONFIGS = [(0.0, np.pi), (2.0, np.pi), (0.0, -np.pi), (0.0, 3 * np.pi), (2.0, -np.pi)]  # (heading, mirror)


@pytest.fixture(scope="module")
def pf_runs():
    """PF estimates ``(T, 4)`` for every (heading, mirror) of ``CONFIGS``: one kernel, vmapped."""
    xs, x0, raw_bearing, rng_z = _pf_track()
    pf = filters.build_pf(_heading_model(_ambiguous_noise(0.02, np.pi)), 2000)
    prior = gmm.from_gaussian(jnp.asarray(x0), jnp.asarray(P0_PF))
    t = jnp.arange(1, T_PF + 1)

    def one(heading, mirror):
        zs = jnp.stack([jnp.asarray(_wrap(raw_bearing)) - heading, jnp.asarray(rng_z)], axis=1)
        zs = zs.at[:, 0].set(jnp.mod(zs[:, 0] + jnp.pi, 2 * jnp.pi) - jnp.pi)
        noise = pf.params.model.measurement_noise
        params = pf.params._replace(
            model=pf.params.model._replace(
                measurement_noise=noise._replace(means=noise.means.at[1, 0].set(mirror))
            )
        )
        inputs = StepInputs(t=t, aux=jnp.full((T_PF,), heading))
        return filters.run(pf, zs, inputs, params=params, key=jax.random.PRNGKey(7), prior=prior)[1].mean

    h, m = (jnp.asarray([c[i] for c in CONFIGS]) for i in (0, 1))
    means = np.asarray(jax.jit(jax.vmap(one))(h, m))
    return dict(zip(CONFIGS, means))


def test_pf_gm_angular_noise_crossing_pi_equals_the_rotated_frame(pf_runs):
    """The same track seen from a sensor heading 0 (the bearing crosses ±pi) and heading 2 rad (the
    bearings stay near -2.4..-0.9 rad, away from ±pi), same key: the same particles, so the same
    estimates up to rounding."""
    xs = _pf_track()[0]
    cross, rotated = pf_runs[(0.0, np.pi)], pf_runs[(2.0, np.pi)]
    bearings = np.arctan2(xs[:, 2], xs[:, 0])
    assert bearings.max() > 3.0 and bearings.min() < -3.0  # the track does cross ±pi
    np.testing.assert_allclose(cross, rotated, rtol=0, atol=1e-8)
    rmse = np.sqrt(np.mean((cross[:, [0, 2]] - xs[:, [0, 2]]) ** 2))
    assert rmse < 5.0, rmse  # the filter tracks (the range alone pins the target to a circle)


def test_pf_gm_component_means_act_on_the_circle(pf_runs):
    """A component mean of pi, -pi or 3 pi is the same noise on the circle: each component's residual
    ``z - h(x) - r_j`` is wrapped, so the estimates agree (wrapping only ``z - h(x)`` loses the
    ambiguity component for two of the three and gives different estimates)."""
    base = pf_runs[(0.0, np.pi)]
    for key in [(0.0, -np.pi), (0.0, 3 * np.pi), (2.0, -np.pi)]:
        np.testing.assert_allclose(pf_runs[key], base, rtol=0, atol=1e-8)


def test_pf_one_update_with_angular_gm_noise_matches_numpy():
    """One weighting step from hand-made particles (no resampling) against a NumPy density with each
    component's residual wrapped."""
    rng = np.random.default_rng(0)
    n = 2000
    noise = _ambiguous_noise(0.3, np.pi)
    pf = filters.build_pf(_heading_model(noise), n, ess_threshold=0.0)
    bearing, rng_x = rng.uniform(-np.pi, np.pi, n), rng.normal(60.0, 3.0, n)  # all around the sensor
    x = np.stack(
        [rng_x * np.cos(bearing), rng.normal(size=n), rng_x * np.sin(bearing), rng.normal(size=n)], 1
    )
    state = filters.pf.PFState(jnp.asarray(x), jnp.full((n,), -np.log(n)))
    z = np.array([0.5, 60.0])
    inputs = StepInputs(t=jnp.ones(()), aux=jnp.zeros(()))
    _, info = jax.jit(pf.update)(pf.params, state, jnp.asarray(z), inputs, key=jax.random.key(0))
    pred = np.stack([np.arctan2(x[:, 2], x[:, 0]), np.hypot(x[:, 0], x[:, 2])], axis=1)
    means, var = np.asarray(noise.means), np.array([SIGMA_B**2, SIGMA_R**2])
    lik = np.zeros(n)
    for wj, rj in zip([0.7, 0.3], means):
        e = z - pred - rj
        e[:, 0] = _wrap(e[:, 0])
        lik += wj * np.exp(-0.5 * np.sum(e**2 / var, axis=1)) / (2 * np.pi * np.sqrt(var.prod()))
    w = lik / lik.sum()
    np.testing.assert_allclose(info.mean, w @ x, rtol=1e-9)
    np.testing.assert_allclose(info.loglik, np.log(lik.mean()), rtol=1e-9)
