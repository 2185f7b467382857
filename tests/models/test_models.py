"""Scenario simulators and true-noise samplers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import mixture as gmm
from gmjax.models import noise, simulate
from gmjax.scenarios import uwb_velocity
from gmjax.scenarios.gamma_system import gamma_system
from gmjax.scenarios.glint_range_bearing import range_bearing
from gmjax.scenarios.jump_system import jump_system


def test_glint_moments_within_standard_error():
    n = 200_000
    keys = jax.random.split(jax.random.key(0), n)
    draws = np.asarray(jax.vmap(lambda k: noise.glint(k, 1.5, 2.0, 3.0, 0.1))(keys))
    var = float(noise.glint_variance(2.0, 3.0, 0.1))
    assert abs(draws.mean() - 1.5) < 5 * np.sqrt(var / n)
    fourth = np.mean((draws - draws.mean()) ** 4)
    assert abs(draws.var() - var) < 5 * np.sqrt((fourth - draws.var() ** 2) / n)


def test_jump_system_process_noise_matches_eq50_first_two_moments():
    sc = jump_system()
    q_mean, q_cov = gmm.moments(sc.model.process_noise)
    n = 100_000
    draws = np.asarray(
        jax.vmap(lambda k: sc.sample_process_noise(k, 1))(jax.random.split(jax.random.key(1), n))
    )[:, 0]
    assert abs(draws.mean() - float(q_mean[0])) < 5 * np.sqrt(float(q_cov[0, 0]) / n)
    fourth = np.mean((draws - draws.mean()) ** 4)
    assert abs(draws.var() - float(q_cov[0, 0])) < 5 * np.sqrt((fourth - draws.var() ** 2) / n)


def test_jump_system_time_index_convention():
    sc = jump_system()
    x = jnp.array([2.0])
    # eq 48: z = x^2/20 + v for t = k+1 <= 80, z = 3x - 4 + v afterwards
    np.testing.assert_allclose(sc.model.h(x, 80), [0.2])
    np.testing.assert_allclose(sc.model.h(x, 81), [2.0])
    # eq 45: x_{k+1} uses cos(1.2 k), i.e. f(x, t) uses cos(1.2 (t - 1))
    np.testing.assert_allclose(sc.model.f(x, 1), 1.0 + 50 / 5 + 8.0)
    xs, zs, ts = simulate(sc, jax.random.key(2))
    assert xs.shape == (121, 1) and zs.shape == (120, 1)
    np.testing.assert_array_equal(ts, np.arange(1, 121))


def test_simulate_is_reproducible_and_noise_is_additive():
    sc = jump_system()._replace(n_steps=5)
    a = simulate(sc, jax.random.key(3))
    b = simulate(sc, jax.random.key(3))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_range_bearing_truth_accelerates_in_y():
    sc = range_bearing()
    xs, zs, _ = simulate(sc, jax.random.key(4))
    assert xs.shape == (1001, 4) and zs.shape == (1000, 2)
    # v_y grows by 70 m/s^2 * 10 s = 700 m/s, up to the tiny process noise
    assert abs(float(xs[-1, 3] - xs[0, 3]) - 700.0) < 5.0
    # x position follows the 240 m/s velocity
    assert abs(float(xs[-1, 0]) - (1000 + 2400)) < 20.0
    assert np.all(np.isfinite(zs))


def test_range_bearing_float32_simulates_float32_under_x64():
    # the glint's Laplace scale once divided by a NumPy float64 and promoted the measurements
    sc = range_bearing(duration=0.05, dtype=jnp.float32)
    xs, zs, _ = simulate(sc, jax.random.key(5))
    assert xs.dtype == jnp.float32 and zs.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(zs)))


def _moments_within_se(draws, mean, cov, n_se=5):
    n = len(draws)
    assert np.all(np.abs(draws.mean(0) - mean) < n_se * np.sqrt(np.diag(cov) / n))
    dev = draws - draws.mean(0)
    se_var = np.sqrt((np.mean(dev**4, 0) - draws.var(0) ** 2) / n)
    assert np.all(np.abs(draws.var(0) - np.diag(cov)) < n_se * se_var)


def test_seed001_gamma_system():
    sc = gamma_system(gamma_scale=2.0)  # the scale-2 variant (MATLAB's gamrnd(3, 2))
    n = 100_000
    draws = np.asarray(
        jax.vmap(lambda k: sc.sample_process_noise(k, 1))(jax.random.split(jax.random.key(5), n))
    )
    _moments_within_se(draws, np.array([6.0]), np.array([[12.0]]))  # Ga(shape 3, scale 2)
    np.testing.assert_allclose(sc.model.h(jnp.array([2.0]), 30), [0.8])
    np.testing.assert_allclose(sc.model.h(jnp.array([2.0]), 31), [-1.0])
    np.testing.assert_allclose(sc.model.f(jnp.array([2.0]), 1), [1.0])  # sin(0) at the first step
    xs, zs, _ = simulate(sc, jax.random.key(6))
    assert xs.shape == (61, 1) and np.all(np.isfinite(zs))


def test_seed001_gamma_default_reading_matches_the_moments_of_eq47():
    """Default Ga(3, 2) = shape 3, scale sqrt(2): its moments are eq 47's (the paper's fit of it)."""
    from gmjax.scenarios.gamma_system import GAMMA_PROCESS_NOISE, eq47_moments

    w, m, v = (np.asarray(a) for a in GAMMA_PROCESS_NOISE)
    mean47 = float(np.sum(w * m))  # from the formula, not from the module
    var47 = float(np.sum(w * (v + (m - mean47) ** 2)))
    assert (mean47, var47) == pytest.approx(eq47_moments(), rel=1e-12)
    assert mean47 == pytest.approx(4.246, abs=5e-4) and var47 == pytest.approx(6.008, abs=5e-4)
    sc = gamma_system()
    draws = np.asarray(
        jax.vmap(lambda k: sc.sample_process_noise(k, 1))(jax.random.split(jax.random.key(5), 100_000))
    )
    _moments_within_se(draws, np.array([3 * np.sqrt(2.0)]), np.array([[6.0]]))  # Ga(shape 3, scale sqrt 2)
    # the reading agrees with eq 47 to three digits; scale 2 misses by 40 % (mean) and 100 % (variance)
    assert abs(3 * np.sqrt(2.0) - mean47) / mean47 < 1e-3 and abs(6.0 - var47) / var47 < 2e-3


def test_seed001_gamma_initial_update_measures_x0_before_any_transition():
    """initial_update: step 1 is k = 0 (identity, no noise), z_0 = 0.2 x_0^2; later steps are eq 44 at k = t - 1."""
    sc = gamma_system(n_steps=4, initial_update=True)
    xs, zs, ts = simulate(sc, jax.random.key(8))
    assert xs.shape == (6, 1) and zs.shape == (5, 1)
    np.testing.assert_array_equal(xs[1], xs[0])  # x at k = 0 is the initial state itself
    np.testing.assert_allclose(zs[:, 0], 0.2 * xs[1:, 0] ** 2, atol=0.02)  # v ~ N(0, 1e-5)
    np.testing.assert_allclose(sc.model.f(jnp.array([2.0]), 1), [2.0])
    np.testing.assert_allclose(sc.model.f(jnp.array([2.0]), 2), [1.0])  # k = 1: sin(0)
    np.testing.assert_allclose(sc.model.h(jnp.array([2.0]), 31), [0.8])  # k = 30: still quadratic
    np.testing.assert_allclose(sc.model.h(jnp.array([2.0]), 32), [-1.0])
    from gmjax.filters import StepInputs

    q0 = sc.model.noise_at(sc.model.process_noise, StepInputs(t=jnp.asarray(1)))
    q1 = sc.model.noise_at(sc.model.process_noise, StepInputs(t=jnp.asarray(2)))
    assert int(q0.mask.sum()) == 1 and float(q0.weights.sum()) == 1.0 and float(q0.covs[0, 0, 0]) < 1e-11
    np.testing.assert_array_equal(q1.means, sc.model.process_noise.means)
    # differences after k = 0 are eq 44's
    w = xs[2:, 0] - 0.5 * xs[1:-1, 0] - np.sin(0.04 * np.pi * np.arange(0, 4))
    assert np.all(w > 0)  # Gamma draws are positive


def test_seed004_noises_match_the_mixtures_the_filters_assume():
    sc = uwb_velocity.synthetic(3, 0.1)
    np.testing.assert_allclose(sc.model.measurement_noise.means[:, 0], 0.1 * np.array([-50, 10, 30, 50, 80]))
    n = 100_000
    keys = jax.random.split(jax.random.key(7), n)
    v = np.asarray(jax.vmap(lambda k: sc.sample_process_noise(k, 1))(keys))
    q_mean, q_cov = (np.asarray(a) for a in gmm.moments(sc.model.process_noise))
    _moments_within_se(v, q_mean, q_cov - 1e-9 * np.eye(2))
    # the process noise lies on the line spanned by (dt, 1) (eq 20)
    np.testing.assert_allclose(v[:, 0], uwb_velocity.DT * v[:, 1], rtol=1e-12)
    w = np.asarray(jax.vmap(lambda k: sc.sample_measurement_noise(k, 1))(keys))
    r_mean, r_cov = (np.asarray(a) for a in gmm.moments(sc.model.measurement_noise))
    _moments_within_se(w, r_mean, r_cov)


def test_seed004_uwb_tables_and_bad_arguments():
    sc = uwb_velocity.uwb("y")
    assert int(gmm.n_active(sc.model.process_noise)) == 9
    assert int(gmm.n_active(sc.model.measurement_noise)) == 2
    import pytest

    with pytest.raises(ValueError, match="axis"):
        uwb_velocity.uwb("z")
    with pytest.raises(ValueError, match="model"):
        uwb_velocity.synthetic(4, 1.0)
