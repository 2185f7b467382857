"""Tests for the satellite scenario of seed 002 §V-C: orbit mechanics, radar geometry, the prior GMM."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from gmjax.pcrb import build_pcrb_gmm, pcrb_mc
from gmjax.quadrature import smolyak
from gmjax.scenarios import satellite_pass
from gmjax.scenarios.satellite_pass import (
    elements_to_rv,
    kepler_propagate,
    radar_measurement,
    rv_to_elements,
    satellite,
)
from gmjax.split import split_axis, uniform_library

X0 = np.asarray(satellite_pass.SATELLITE_STATE)


def _two_body(t, y):
    r = y[:3]
    return np.concatenate([y[3:], -satellite_pass.MU_EARTH * r / np.linalg.norm(r) ** 3])


def test_table_ii_state_has_table_iii_elements():
    el = np.asarray(jax.jit(rv_to_elements)(jnp.asarray(X0)))
    a, e, inc, raan, argp, M = el
    ta, te, ti, traan, targp, tnu = satellite_pass.SATELLITE_ELEMENTS
    assert a == pytest.approx(ta, abs=2e-3)
    assert e == pytest.approx(te, abs=1e-6)
    assert math.degrees(inc) == pytest.approx(ti, abs=1e-5)
    assert math.degrees(raan) % 360 == pytest.approx(traan, abs=1e-5)
    assert math.degrees(argp) == pytest.approx(targp, abs=1e-3)
    # mean anomaly -> true anomaly
    E = M
    for _ in range(20):
        E = E - (E - e * math.sin(E) - M) / (1 - e * math.cos(E))
    nu = 2 * math.atan2(math.sqrt(1 + e) * math.sin(E / 2), math.sqrt(1 - e) * math.cos(E / 2))
    assert math.degrees(nu) % 360 == pytest.approx(tnu, abs=1e-3)
    back = np.asarray(jax.jit(elements_to_rv)(jnp.asarray(el)))
    np.testing.assert_allclose(back, X0, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("dt", [5.0, 3000.0, -2000.0])
def test_kepler_propagation_matches_numerical_integration(dt):
    got = np.asarray(jax.jit(kepler_propagate)(jnp.asarray(X0), dt))
    sol = solve_ivp(_two_body, (0.0, dt), X0, rtol=1e-12, atol=1e-12, method="DOP853")
    np.testing.assert_allclose(got[:3], sol.y[:3, -1], atol=1e-6)
    np.testing.assert_allclose(got[3:], sol.y[3:, -1], atol=1e-9)


def test_kepler_state_transition_matrix_matches_finite_differences():
    stm = np.asarray(jax.jit(jax.jacfwd(kepler_propagate))(jnp.asarray(X0), 600.0))
    fd = np.zeros((6, 6))
    prop = jax.jit(kepler_propagate)
    for j in range(6):
        h = 1e-3 if j < 3 else 1e-6
        e = np.zeros(6)
        e[j] = h
        fd[:, j] = (
            np.asarray(prop(jnp.asarray(X0 + e), 600.0)) - np.asarray(prop(jnp.asarray(X0 - e), 600.0))
        ) / (2 * h)
    np.testing.assert_allclose(stm, fd, rtol=1e-6, atol=1e-8)


def test_geodetic_site_and_radar_geometry():
    np.testing.assert_allclose(
        satellite_pass.geodetic_to_ecef(0.0, 0.0, 0.0), [satellite_pass.WGS84_A, 0, 0], atol=1e-9
    )
    np.testing.assert_allclose(satellite_pass.geodetic_to_ecef(90.0, 0.0, 0.0)[2], 6356.752314245, atol=1e-6)
    site = satellite_pass.geodetic_to_ecef(*satellite_pass.RADAR_SITE)
    # a point straight above the site (at t = 0, theta0 = 0) has elevation 90 deg
    up = satellite_pass._enu_matrix(satellite_pass.RADAR_SITE[0], satellite_pass.RADAR_SITE[1])[2]
    x = jnp.asarray(np.concatenate([site + 500.0 * up, np.zeros(3)]))
    z = np.asarray(radar_measurement(x, 0.0, 0.0))
    assert z[0] == pytest.approx(500.0, rel=1e-12)
    assert z[2] == pytest.approx(math.pi / 2, abs=1e-9)


def test_range_rate_is_the_time_derivative_of_range():
    """Rdot against a central difference of R along the trajectory with the Earth rotating."""
    th0 = 1.3
    prop = jax.jit(kepler_propagate)
    meas = jax.jit(lambda x, t: radar_measurement(x, t, th0, range_rate=True))
    x = jnp.asarray(X0)
    h = 0.5
    Rp = float(meas(prop(x, h), h)[0])
    Rm = float(meas(prop(x, -h), -h)[0])
    assert float(meas(x, 0.0)[3]) == pytest.approx((Rp - Rm) / (2 * h), rel=1e-7)


@pytest.fixture(scope="module")
def short_scenario():
    return satellite(max_steps=12)


def test_satellite_scenario_layout(short_scenario):
    sc = short_scenario
    assert sc.times[0] == pytest.approx(-33.320833 * 3600)
    np.testing.assert_allclose(sc.times[1:], 5.0 * np.arange(len(sc.times) - 1))
    # t = 0 is the rise of the reference orbit over the site's horizon (the chosen epoch)
    x_t0 = jax.jit(kepler_propagate)(jnp.asarray(X0), -sc.times[0])
    assert abs(float(radar_measurement(x_t0, 0.0, sc.theta0)[2])) < 1e-9
    assert float(radar_measurement(kepler_propagate(x_t0, 5.0), 5.0, sc.theta0)[2]) > 0
    # the model's f(x, n) maps x_n at times[n] to x_{n+1} at times[n+1]
    x1 = jax.jit(sc.model.f)(jnp.asarray(X0), 0)
    np.testing.assert_allclose(x1, x_t0, rtol=1e-12)
    np.testing.assert_allclose(np.diag(sc.model.R), [4e-6, 1e-6, 1e-6])
    np.testing.assert_allclose(np.diag(sc.model.Q), [1e-6] * 3 + [1e-12] * 3)


def test_satellite_prior_gmm_is_a_split_along_semimajor_axis(short_scenario):
    """The 49 component means map back (eq 25) to points el0 + mu_i a on the split line of eq 20."""
    gm = short_scenario.prior_gm
    lib = uniform_library(0.25)
    assert gm.capacity == lib.size == 49
    np.testing.assert_allclose(float(jnp.sum(gm.weights)), 1.0, rtol=1e-12)
    to_el = jax.jit(jax.vmap(rv_to_elements))
    el_means = np.asarray(to_el(gm.means))
    x0 = jnp.asarray(X0)
    G = np.asarray(jax.jacfwd(rv_to_elements)(x0))
    P_el = G @ np.diag([1e-2] * 3 + [1e-8] * 3) @ G.T
    a_col = np.asarray(split_axis(P_el, 0))
    el0 = np.asarray(rv_to_elements(x0))
    want = el0[None] + lib.means[:, None] * a_col[None]
    np.testing.assert_allclose(el_means, want, rtol=1e-9, atol=1e-11)
    for k in range(49):
        assert np.all(np.linalg.eigvalsh(np.asarray(gm.covs[k])) > 0)


@pytest.mark.slow
def test_satellite_gmm_pcrb_close_to_monte_carlo_on_a_short_arc(short_scenario):
    sc = short_scenario
    T = len(sc.times) - 1
    res = build_pcrb_gmm(sc.model, smolyak(6, 2), T, sc.config)(sc.prior_gm)
    mc = pcrb_mc(sc.model, T, 4000, key=jax.random.PRNGKey(3), chunk_size=1000, progress=False)
    b, bm, se = (np.asarray(a) for a in (res.bound, mc.bound, mc.info.bound_stderr))
    pos = lambda B: np.trace(B[:, :3, :3], axis1=1, axis2=2)  # noqa: E731
    # position-bound standard error over chunks (diagonal errors combined in quadrature, upper bound)
    se_pos = np.sqrt(np.sum(se[:, [0, 1, 2], [0, 1, 2]] ** 2, axis=1))
    z = np.abs(pos(b)[1:] - pos(bm)[1:]) / se_pos[1:]
    assert np.all(np.asarray(res.info.metric) < 0.01)  # small-covariance case, as in Fig 8
    assert z.max() < 5.0, z
