"""Seed 001 scenarios: the bearings-only tracking setting of §4.2 (eqs 48–52)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import expm

from gmjax import mixture as gmm
from gmjax.models import simulate
from gmjax.scenarios.bearings_only import (
    BEARINGS_PROCESS_NOISE,
    BEARINGS_SENSORS,
    bearings_only,
    turn_rate_schedule,
)


@pytest.fixture(scope="module")
def scenario():
    return bearings_only()


def test_truth_is_the_expm_of_the_turning_model(scenario):
    """The truth of Särkkä's demo, written with SciPy's expm of F(a) dt, step by step."""
    dt = 0.01
    a = turn_rate_schedule(500, dt)
    x = np.array([0.0, 0.0, 1.0, 0.0])
    want = [x]
    for k in range(500):
        F = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [0, 0, 0, a[k]], [0, 0, -a[k], 0]], float)
        x = expm(F * dt) @ x
        want.append(x)
    xs, zs, ts = simulate(scenario, jax.random.key(0))
    np.testing.assert_allclose(np.asarray(xs), np.array(want), atol=1e-10)
    # unit speed, two quarter turns and a half turn: final heading +x after starting +x
    np.testing.assert_allclose(np.linalg.norm(np.asarray(xs[:, 2:]), axis=1), 1.0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(xs[-1, 2:]), [1.0, 0.0], atol=1e-10)
    assert zs.shape == (500, 2) and ts.shape == (500,)


def test_bearings_never_wrap_and_noise_has_the_paper_std(scenario):
    xs, zs, _ = simulate(scenario, jax.random.key(1))
    xs = np.asarray(xs[1:])
    for i, (sx, sy) in enumerate(BEARINGS_SENSORS):
        true = np.arctan2(xs[:, 1] - sy, xs[:, 0] - sx)  # eq 51
        np.testing.assert_allclose(
            np.asarray(scenario.model.h(jnp.asarray(xs[10]), 10))[i], true[10], rtol=1e-12
        )
        # sensor 1 sees y > s_y, sensor 2 sees y < s_y: no bearing crosses +-pi
        assert np.all(np.sign(xs[:, 1] - sy) == (1 if i == 0 else -1))
        resid = np.asarray(zs[:, i]) - true
        # std 0.1 rad: the sample std of 500 draws lies within 4 standard errors (0.1 / sqrt(2 * 500))
        assert abs(resid.std() - 0.1) < 4 * 0.1 / np.sqrt(1000)
        assert abs(resid.mean()) < 4 * 0.1 / np.sqrt(500)


def test_process_noise_reading_of_eq50(scenario):
    """Eq 50's scalar terms become 4-D components mu_l g and sigma_l^2 Q_1(dt) (see the docstring)."""
    dt = 0.01
    q = scenario.model.process_noise
    w, mu, var = BEARINGS_PROCESS_NOISE
    np.testing.assert_allclose(np.asarray(q.weights), w)
    g = np.array([dt**2 / 2, dt**2 / 2, dt, dt])
    Q1 = np.array(
        [
            [dt**3 / 3, 0, dt**2 / 2, 0],
            [0, dt**3 / 3, 0, dt**2 / 2],
            [dt**2 / 2, 0, dt, 0],
            [0, dt**2 / 2, 0, dt],
        ]
    )
    for l in range(3):  # noqa: E741
        np.testing.assert_allclose(np.asarray(q.means[l]), mu[l] * g, rtol=1e-12)
        np.testing.assert_allclose(np.asarray(q.covs[l]), var[l] * Q1, rtol=1e-12)
    zero = bearings_only(zero_mean_noise=True).model.process_noise
    np.testing.assert_allclose(np.asarray(zero.means), 0.0)
    # filter prior eq 52 and the linear Wiener-velocity model of eq 49
    m, P = gmm.moments(scenario.model.prior)
    np.testing.assert_allclose(np.asarray(m), 0.0)
    np.testing.assert_allclose(np.asarray(P), np.diag([0.1, 0.1, 10, 10]))
    x = jnp.array([1.0, 2.0, 3.0, 4.0])
    np.testing.assert_allclose(np.asarray(scenario.model.f(x, 1)), [1.03, 2.04, 3.0, 4.0], rtol=1e-12)


def test_float32_scenario_simulates():
    sc = bearings_only(dtype=jnp.float32, n_steps=50)
    xs, zs, _ = simulate(sc, jax.random.key(2))
    assert xs.dtype == jnp.float32 and zs.dtype == jnp.float32
    assert bool(jnp.all(jnp.isfinite(zs)))
