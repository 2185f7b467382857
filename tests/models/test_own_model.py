"""A user's own model: irregular time steps with Q(dt), control inputs, angles crossing ±pi,
a scenario from a model in one call."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import filters, reduction
from gmjax import mixture as gmm
from gmjax.filters import StepInputs
from gmjax.models import StateSpaceModel, inputs_from_times, scenario_from_model, simulate
from gmjax.models import library as lib

jax.config.update("jax_enable_x64", True)


# --- irregular time steps ----------------------------------------------------------------------


def _cv_closed_form(dt, q):
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return np.kron(np.eye(2), F), np.kron(np.eye(2), Q)


def test_irregular_dt_kf_equals_closed_form_cv_kf():
    q, T = 0.3, 15
    rng = np.random.default_rng(0)
    times = np.cumsum(rng.uniform(0.05, 2.5, T))
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    R = np.diag([0.5, 0.8])
    m0, P0 = np.array([0.0, 1.0, 0.0, -1.0]), np.diag([4.0, 1.0, 4.0, 1.0])
    zs = rng.normal(size=(T, 2)) * 3
    zs[4] = np.nan  # a missing measurement stays a NaN row: predict only
    model = lib.state_space_model(
        lib.constant_velocity(2, q),
        lib.cartesian_position((0, 2), 4, R),
        gmm.from_gaussian(jnp.asarray(m0), jnp.asarray(P0)),
    )
    inputs = inputs_from_times(times)
    _, infos = filters.run(filters.build_kf(model), jnp.asarray(zs), inputs)
    m, P, prev = m0, P0, 0.0
    for k, t in enumerate(times):
        F, Q = _cv_closed_form(t - prev, q)
        prev = t
        m, P = F @ m, F @ P @ F.T + Q
        if not np.isnan(zs[k]).any():
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            m = m + K @ (zs[k] - H @ m)
            A = np.eye(4) - K @ H
            P = A @ P @ A.T + K @ R @ K.T
        np.testing.assert_allclose(infos.mean[k], m, atol=1e-10, rtol=1e-10)
        np.testing.assert_allclose(infos.cov[k], P, atol=1e-10, rtol=1e-10)
    # the EKF, UKF and the Gaussian sum filter on the same model agree with the KF (linear model)
    for f in (filters.build_ekf(model), filters.build_ukf(model), filters.build_gsf(model, "kf", None, 1)):
        _, other = filters.run(f, jnp.asarray(zs), inputs)
        np.testing.assert_allclose(other.mean, infos.mean, atol=1e-9)
    # and the RTS smoother follows the same dt per step
    sm = filters.rts_smoother(model, infos.mean, infos.cov, inputs, method="kf")
    F, Q = _cv_closed_form(times[-1] - times[-2], q)
    Pp = F @ np.asarray(infos.cov[-2]) @ F.T + Q
    np.testing.assert_allclose(sm.predicted_cov[-2], Pp, atol=1e-10)


def test_simulate_irregular_times_scales_process_noise_with_dt():
    q = 2.0
    model = lib.state_space_model(
        lib.random_walk(1, q),
        lib.cartesian_position((0,), 1, 0.01),
        gmm.from_gaussian(jnp.zeros(1), jnp.eye(1) * 1e-6),
    )
    times = np.array([0.5, 0.6, 3.6])
    sc = scenario_from_model(model, 3, inputs=inputs_from_times(times), name="rw")
    xs, zs, inp = jax.vmap(lambda k: simulate(sc, k))(jax.random.split(jax.random.PRNGKey(0), 20_000))
    assert isinstance(inp, StepInputs)
    np.testing.assert_allclose(inp.dt[0], np.diff(np.concatenate([[0.0], times])))
    incr = np.diff(np.asarray(xs[:, :, 0]), axis=1)  # (N, 3)
    var = incr.var(axis=0)
    expected = q * np.diff(np.concatenate([[0.0], times]))
    se = expected * np.sqrt(2 / incr.shape[0])
    assert np.all(np.abs(var - expected) < 5 * se), (var, expected)


def test_inputs_from_times_rejects_bad_times():
    with pytest.raises(ValueError, match="times"):
        inputs_from_times([1.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="times"):
        inputs_from_times([[1.0]])


# --- control inputs ----------------------------------------------------------------------------


def test_control_input_f_x_u_t_matches_numpy_kf_and_old_models_still_work():
    a, b, q, r = 0.9, 0.5, 0.2, 0.3
    T = 12
    rng = np.random.default_rng(1)
    us = rng.normal(size=(T, 1))
    zs = rng.normal(size=(T, 1))

    def f(x, u, t):  # a control input: call="u,t"
        return a * x + b * u

    model = StateSpaceModel(
        f=f,
        h=lambda x, u, t: x,
        process_noise=gmm.from_gaussian(jnp.zeros(1), q * jnp.eye(1)),
        measurement_noise=gmm.from_gaussian(jnp.zeros(1), r * jnp.eye(1)),
        prior=gmm.from_gaussian(jnp.zeros(1), jnp.eye(1)),
        call="u,t",
    )
    inputs = StepInputs(t=jnp.arange(1, T + 1), control=jnp.asarray(us))
    for build in (filters.build_kf, filters.build_ekf, filters.build_ckf):
        _, infos = filters.run(build(model), jnp.asarray(zs), inputs)
        m, P = 0.0, 1.0
        for k in range(T):
            m, P = a * m + b * us[k, 0], a * a * P + q
            K = P / (P + r)
            m, P = m + K * (zs[k, 0] - m), (1 - K) * P
            np.testing.assert_allclose(infos.mean[k, 0], m, rtol=1e-10)
    # vmap over control sequences == loop
    batch = jnp.stack([jnp.asarray(us), -jnp.asarray(us)])
    kf = filters.build_kf(model)
    vm = jax.vmap(lambda u: filters.run(kf, jnp.asarray(zs), inputs._replace(control=u))[1].mean)(batch)
    for i in range(2):
        loop = filters.run(kf, jnp.asarray(zs), inputs._replace(control=batch[i]))[1].mean
        np.testing.assert_allclose(vm[i], loop, rtol=1e-12)
    # a control-free model keeps f(x, t), and call="inputs" hands over the whole StepInputs
    seen = {}

    def g(x, inp):
        seen["type"] = type(inp).__name__
        return a * x + b * inp.control

    m2 = model._replace(f=g, h=lambda x, inp: x, call="inputs")
    _, infos2 = filters.run(filters.build_kf(m2), jnp.asarray(zs), inputs)
    np.testing.assert_allclose(infos2.mean, infos.mean, rtol=1e-12)
    assert seen["type"] == "StepInputs"
    with pytest.raises(ValueError, match="call"):
        filters.build_kf(model._replace(call="x,y"))


def test_call_convention_is_said_not_sniffed_and_a_wrong_arity_is_named():
    """``call`` is given (default ``"t"``); a function called with the wrong arity raises a
    ``TypeError`` that names the convention it was called by, at build time."""
    noise = gmm.from_gaussian(jnp.zeros(1), jnp.eye(1))
    model = StateSpaceModel(
        f=lambda x, u, t: x + u,
        h=lambda x, u, t: x,
        process_noise=noise,
        measurement_noise=noise,
        prior=noise,
    )
    assert model.call == "t"
    with pytest.raises(TypeError, match=r"model\.f: called as f\(x, t\) \(call='t'\).*call='u,t'"):
        filters.build_ekf(model)
    with pytest.raises(ValueError, match="call.*'auto'.*removed"):
        filters.build_kf(model._replace(call="auto"))
    filters.build_ekf(model._replace(call="u,t"))  # said: builds

    # a process noise of the state says so; a three-parameter one called without the flag is named
    def noise_at(q, inputs, x):
        return q._replace(covs=q.covs * (1.0 + x[0] ** 2))

    sd = StateSpaceModel(
        f=lambda x, t: x,
        h=lambda x, t: x,
        process_noise=noise,
        measurement_noise=noise,
        prior=noise,
        process_noise_at=noise_at,
    )
    zs, inputs = jnp.ones((3, 1)), StepInputs(t=jnp.arange(1, 4))
    with pytest.raises(TypeError, match=r"process_noise_at\(noise, inputs\).*state_dependent_noise=True"):
        filters.run(filters.build_ekf(sd), zs, inputs)
    _, infos = filters.run(filters.build_ekf(sd._replace(state_dependent_noise=True)), zs, inputs)
    assert np.all(np.isfinite(np.asarray(infos.mean)))
    with pytest.raises(ValueError, match="state_dependent_noise: True needs a process_noise_at"):
        filters.build_ekf(sd._replace(process_noise_at=None, state_dependent_noise=True))


# --- angles across ±pi -------------------------------------------------------------------------

T_ANG = 30
P0_ANG = np.diag([25.0, 1.0, 25.0, 1.0])
MEASUREMENTS = {
    "bearing_range": lib.bearing_range((0, 2), (0.01, 1.0)),
    "bearings_only": lib.bearings_only((0, 2), 0.01**2),
}


def _track(theta):
    """A target passing behind the sensor at bearing ±pi (theta=0) or the same track rotated by
    theta; the prior mean is off the truth by a rotated offset."""
    c, s = np.cos(theta), np.sin(theta)
    Rm = np.array([[c, -s], [s, c]])
    p0, v = Rm @ np.array([-100.0, 10.0]), Rm @ np.array([0.5, -0.7])
    xs = np.stack([[p0[0] + v[0] * k, v[0], p0[1] + v[1] * k, v[1]] for k in range(1, T_ANG + 1)])
    off, dv = Rm @ np.array([3.0, -2.0]), Rm @ np.array([0.3, -0.2])
    x0 = np.array([p0[0] + off[0], v[0] + dv[0], p0[1] + off[1], v[1] + dv[1]])
    return xs, x0


def _measure(meas, xs):
    w = np.random.default_rng(0).multivariate_normal(np.zeros(meas.dim), np.asarray(meas.R), size=len(xs))
    z = np.stack([np.asarray(meas.h(jnp.asarray(x))) for x in xs]) + w
    z[:, 0] = np.mod(z[:, 0] + np.pi, 2 * np.pi) - np.pi
    return z


def _angle_model(meas, wrap=True):
    prior = gmm.from_gaussian(jnp.zeros(4), jnp.asarray(P0_ANG))
    model = lib.state_space_model(lib.constant_velocity(2, 0.1), meas, prior)
    return model if wrap else model._replace(angle_dims=())


def _angle_filter(name, model):
    R = model.measurement_noise.covs[0]
    if name == "gsf":
        glint = model._replace(measurement_noise=lib.glint_mixture(R, 0.1, 5.0))
        return filters.build_gsf(glint, "ukf", reduction.Runnalls(num_out=4), 4, track_ise=False)
    if name == "imm":
        wide = model._replace(process_noise=gmm.from_gaussian(jnp.zeros(4), 10 * model.process_noise.covs[0]))
        return filters.build_imm([model, wide], [[0.95, 0.05], [0.05, 0.95]], filter="ukf")
    if name == "pf":
        return filters.build_pf(model, 4000)
    build = {
        "ekf": filters.build_ekf,
        "ukf": lambda m: filters.build_ukf(m, 1.0, 2.0, 0.0),
        "ckf": filters.build_ckf,
        "ghkf": filters.build_ghkf,
        "sgkf": filters.build_sgkf,
        "sckf": filters.build_sckf,
    }[name]
    return build(model)


@functools.cache
def _angle_errors(meas_name, filter_name, wrap=True):
    """Position RMSE ``(2,)`` on the track crossing ±pi and on the same track rotated by pi (one
    compiled kernel, vmapped over the two)."""
    meas = MEASUREMENTS[meas_name]
    tracks = [_track(theta) for theta in (0.0, np.pi)]
    zs = jnp.asarray(np.stack([_measure(meas, xs) for xs, _ in tracks]))
    x0s = jnp.asarray(np.stack([x0 for _, x0 in tracks]))
    truth = np.stack([xs for xs, _ in tracks])
    filt = _angle_filter(filter_name, _angle_model(meas, wrap))

    def one(z, x0):
        prior = gmm.from_gaussian(x0, jnp.asarray(P0_ANG))
        return filters.run(filt, z, key=jax.random.PRNGKey(0), prior=prior)[1].mean

    means = np.asarray(jax.jit(jax.vmap(one))(zs, x0s))
    return np.sqrt(np.mean((means[..., [0, 2]] - truth[..., [0, 2]]) ** 2, axis=(1, 2)))


FILTERS = ["ekf", "ukf", "ckf", "ghkf", "sgkf", "sckf", "gsf", "imm", "pf"]


@pytest.mark.parametrize("filter_name", FILTERS)
@pytest.mark.parametrize(
    "meas_name", ["bearing_range", pytest.param("bearings_only", marks=pytest.mark.slow)]
)
def test_every_filter_is_unaffected_by_the_pi_crossing(meas_name, filter_name):
    cross, rotated = _angle_errors(meas_name, filter_name)
    if filter_name == "pf":  # the rotated run draws different process noise: Monte Carlo spread
        assert 0.8 < cross / rotated < 1.25, (cross, rotated)
    else:  # rotating by pi maps every symmetric sigma-point set onto itself: equal to rounding
        np.testing.assert_allclose(cross, rotated, rtol=1e-8)


def test_bearings_only_crossing_fast_subset():
    for name in ("ekf", "ukf"):
        cross, rotated = _angle_errors("bearings_only", name)
        np.testing.assert_allclose(cross, rotated, rtol=1e-8)


def test_without_angle_dims_the_crossing_breaks_the_filters():
    """The negative control: the same runs with the bearing declared an ordinary number."""
    ekf_wrapped = _angle_errors("bearing_range", "ekf")[0]
    ekf_raw = _angle_errors("bearing_range", "ekf", wrap=False)
    assert ekf_raw[0] > 20 * ekf_wrapped  # off the track at the crossing
    np.testing.assert_allclose(ekf_raw[1], ekf_wrapped, rtol=1e-8)  # fine away from ±pi
    ukf_wrapped = _angle_errors("bearings_only", "ukf")[0]
    assert _angle_errors("bearings_only", "ukf", wrap=False)[0] > 1.3 * ukf_wrapped


def test_circular_mean_and_wrap():
    from gmjax.filters._core import circular_mean
    from gmjax.models import wrap_angles

    Z = jnp.array([[np.pi - 0.1, 5.0], [-np.pi + 0.1, 7.0], [np.pi - 0.05, 6.0]])
    w = jnp.array([0.25, 0.25, 0.5])
    mean = circular_mean(Z, w, (0,))
    np.testing.assert_allclose(mean, [np.pi - 0.025, 6.0], rtol=1e-12)
    np.testing.assert_allclose(wrap_angles(jnp.array([3 * np.pi / 2, 1.0]), (0,)), [-np.pi / 2, 1.0])
    with pytest.raises(ValueError, match="angle_dims"):
        filters.build_ekf(_angle_model(MEASUREMENTS["bearing_range"])._replace(angle_dims=(2,)))
