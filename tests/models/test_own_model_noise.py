"""A user's own model, continued: angular Gaussian-mixture noise in the particle filter, the seed 004
bank with irregular dt, controls and per-step noise, and state-dependent process noise."""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import filters
from gmjax import mixture as gmm
from gmjax.filters import StepInputs
from gmjax.mixture import GaussianMixture
from gmjax.models import StateSpaceModel, inputs_from_times
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


# --- the seed 004 bank with irregular dt, a control and the step's process noise -----------------

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from references.bank_np import _kf, _logpdf, _moments  # noqa: E402

T_BANK = 20
H_BANK = np.array([[1.0, 0.0]])
JITTER = 1e-9


def _bank_steps():
    """Irregular times, a control (acceleration) per step and the measurement noise draws."""
    rng = np.random.default_rng(11)
    times = np.cumsum(rng.uniform(0.05, 1.5, T_BANK))
    return times, rng.normal(size=(T_BANK, 1)), rng


def _F(dt):
    return np.array([[1.0, dt], [0.0, 1.0]])


def _B(dt):
    return np.array([[dt**2 / 2], [dt]])


def _rwv_noise(weights, means, variances):
    """Process clusters ``v = (1, 1)^T s`` at the reference ``dt = 1`` (rank one, plus a jitter), as
    ``(weights, means (n, 2), covs (n, 2, 2))``."""
    g = np.ones(2)
    return (
        np.asarray(weights, float),
        np.asarray(means, float)[:, None] * g,
        np.asarray(variances, float)[:, None, None] * np.outer(g, g) + JITTER * np.eye(2),
    )


def _to_dt(dt):
    """``A(dt) = diag(dt, 1)`` maps the reference noise ``(1, 1)^T s`` to ``(dt, 1)^T s``."""
    return np.diag([dt, 1.0])


def _bank_model(process, measurement):
    """Random-walk velocity with an acceleration control at irregular times (``call="inputs"``); the
    process noise follows the step through ``process_noise_at`` (``Q(dt) = A Q(1) A^T``)."""

    def f(x, inputs):
        dt = inputs.dt
        F = jnp.stack(
            [jnp.stack([jnp.ones_like(dt), dt]), jnp.stack([jnp.zeros_like(dt), jnp.ones_like(dt)])]
        )
        B = jnp.stack([dt**2 / 2, dt])
        u = 0.0 if inputs.control is None else inputs.control[0]  # Red-SSG's F: no control
        return F @ x + B * u

    def noise_at(noise, inputs):
        A = jnp.diag(jnp.stack([inputs.dt, jnp.ones_like(inputs.dt)]))
        covs = jnp.einsum("ij,kjl,ml->kim", A, noise.covs, A)
        return noise._replace(means=noise.means @ A.T, covs=covs)

    return StateSpaceModel(
        f=f,
        h=lambda x, inputs: jnp.asarray(H_BANK) @ x,
        process_noise=GaussianMixture.create(*process),
        measurement_noise=GaussianMixture.create(*measurement),
        prior=gmm.from_gaussian(jnp.zeros(2), 10.0 * jnp.eye(2)),
        process_noise_at=noise_at,
        call="inputs",
    )


def _bank_data(process, measurement):
    """A run of the model (truth drawn in NumPy), its :class:`StepInputs` and the true pairs."""
    times, us, rng = _bank_steps()
    dts = np.diff(np.concatenate([[0.0], times]))
    qw, qu, qQ = process
    rw, rb, rR = measurement
    x, zs, active = np.zeros(2), [], []
    for k, dt in enumerate(dts):
        i, j = rng.choice(len(qw), p=qw / qw.sum()), rng.choice(len(rw), p=rw / rw.sum())
        A = _to_dt(dt)
        x = _F(dt) @ x + _B(dt) @ us[k] + rng.multivariate_normal(A @ qu[i], A @ qQ[i] @ A.T)
        zs.append(H_BANK @ x + rng.multivariate_normal(rb[j], rR[j]))
        active.append((i, j))
    inputs = inputs_from_times(times, control=jnp.asarray(us))
    return np.array(zs), inputs._replace(aux=jnp.asarray(active, jnp.int32)), dts, us


def _bank_np(method, zs, dts, us, process, measurement, active):
    """NumPy bank (seed 004 eqs 5–17) with ``F(dt)``, ``B(dt) u`` and ``Q_i(dt)`` per step; eq 17's
    process term uses ``G(dt)^+``, ``G(dt) = (dt, 1)^T``."""
    qw, qu, qQ = (np.asarray(a, float) for a in process)
    rw, rb, rR = (np.asarray(a, float) for a in measurement)
    qw, rw = qw / qw.sum(), rw / rw.sum()
    m, P = np.zeros(2), 10.0 * np.eye(2)
    out = []
    for k, (z, dt) in enumerate(zip(zs, dts)):
        A, F, Bu = _to_dt(dt), _F(dt), _B(dt) @ us[k]
        u_dt = [A @ u + Bu for u in qu]  # the control enters as a known process-noise mean
        Q_dt = [A @ Q @ A.T for Q in qQ]
        if method == "kf-mm":
            qm, qP = _moments(qw, [A @ u for u in qu], Q_dt)
            rm, rP = _moments(rw, rb, rR)
            m, P, _ = _kf(m, P, z, F, H_BANK, qm + Bu, qP, rm, rP)
            out.append(m)
            continue
        keys = [(i, j) for i in range(len(qw)) for j in range(len(rw))]
        post = {(i, j): _kf(m, P, z, F, H_BANK, u_dt[i], Q_dt[i], rb[j], rR[j]) for i, j in keys}
        lw = np.array([np.log(qw[i]) + np.log(rw[j]) + post[i, j][2] for i, j in keys])
        mu = np.exp(lw - lw.max())
        mu /= mu.sum()
        best = keys[int(np.argmax(mu))]
        if method == "gsf-merge":
            m, P = _moments(mu, [post[key][0] for key in keys], [post[key][1] for key in keys])
            out.append(m)
            continue
        if method == "gsf-remove":
            sel = best
        elif method == "matched":
            sel = tuple(int(a) for a in active[k])
        else:
            if method == "red-gsfm":
                x_check = sum(w * post[key][0] for w, key in zip(mu, keys))
            elif method == "red-gsfr":
                x_check = post[best][0]
            else:  # red-dkg
                qm, qP = _moments(qw, [A @ u for u in qu], Q_dt)
                x_check = _kf(m, P, z, F, H_BANK, qm + Bu, qP, *_moments(rw, rb, rR))[0]
            Gp = np.linalg.pinv(np.array([[dt], [1.0]]))
            v = Gp @ (x_check - F @ m - Bu)  # eq 15
            w = z - H_BANK @ x_check  # eq 16
            si = [np.log(qw[i]) + _logpdf(v, Gp @ (A @ qu[i]), Gp @ Q_dt[i] @ Gp.T) for i in range(len(qw))]
            sj = [np.log(rw[j]) + _logpdf(w, rb[j], rR[j]) for j in range(len(rw))]
            sel = (int(np.argmax(si)), int(np.argmax(sj)))  # eq 17
        m, P = post[sel][0], post[sel][1]
        out.append(m)
    return np.array(out)


PROCESS2 = _rwv_noise([0.7, 0.3], [0.0, 1.5], [0.2, 1.0])
MEASUREMENT2 = (np.array([0.8, 0.2]), np.array([[0.0], [2.0]]), np.array([[[0.3]], [[3.0]]]))
NP_METHODS = ["gsf-merge", "gsf-remove", "matched", "kf-mm", "red-gsfm", "red-gsfr", "red-dkg"]


@pytest.mark.parametrize("method", NP_METHODS)
def test_bank_with_irregular_dt_control_and_step_noise_matches_numpy(method):
    zs, inputs, dts, us = _bank_data(PROCESS2, MEASUREMENT2)
    filt = filters.bank.build_bank(_bank_model(PROCESS2, MEASUREMENT2), method)
    _, infos = jax.jit(lambda z, i: filters.run(filt, z, i))(jnp.asarray(zs), inputs)
    ref = _bank_np(method, zs, dts, us, PROCESS2, MEASUREMENT2, np.asarray(inputs.aux))
    np.testing.assert_allclose(np.asarray(infos.mean), ref, rtol=1e-9, atol=1e-9)


def test_bank_gsf_merge_and_remove_equal_the_gsf_with_one_slot():
    """The bank is the Gaussian sum filter of one Gaussian: GSF-merge is the GSF merging everything
    (Runnalls to one component), GSF-remove the GSF keeping the heaviest (capacity 1)."""
    from gmjax import reduction

    zs, inputs, _, _ = _bank_data(PROCESS2, MEASUREMENT2)
    model = _bank_model(PROCESS2, MEASUREMENT2)
    zs = jnp.asarray(zs)
    merge = filters.run(filters.bank.build_bank(model, "gsf-merge"), zs, inputs)[1].mean
    gsf = filters.run(filters.build_gsf(model, "kf", reduction.Runnalls(num_out=1), 1), zs, inputs)[1].mean
    np.testing.assert_allclose(merge, gsf, rtol=1e-10, atol=1e-10)
    remove = filters.run(filters.bank.build_bank(model, "gsf-remove"), zs, inputs)[1].mean
    kept = filters.run(filters.build_gsf(model, "kf", None, 1), zs, inputs)[0].mixture.means[:, 0]
    np.testing.assert_allclose(remove, kept, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize(
    "methods",
    [("red-pkg", "red-ssg"), pytest.param(filters.bank.BANK_METHODS, marks=pytest.mark.slow)],
    ids=["gain-methods", "all"],
)
def test_bank_one_cluster_is_the_closed_form_kf(methods):
    """One cluster per noise: every method is the Kalman filter with ``F(dt)``, ``B(dt) u`` and
    ``Q(dt)`` of each step (the two approximate-gain methods by default; the others are checked
    with two clusters above, all of them in the slow case)."""
    process = _rwv_noise([1.0], [0.5], [0.4])
    measurement = (np.array([1.0]), np.array([[-0.3]]), np.array([[[0.5]]]))
    zs, inputs, dts, us = _bank_data(process, measurement)
    model = _bank_model(process, measurement)
    ref = _bank_np("gsf-merge", zs, dts, us, process, measurement, None)
    for method in methods:
        _, infos = filters.run(filters.bank.build_bank(model, method), jnp.asarray(zs), inputs)
        np.testing.assert_allclose(np.asarray(infos.mean), ref, rtol=1e-9, atol=1e-9, err_msg=method)


# --- state-dependent process noise ----------------------------------------------------------------

Q_SD, R_SD, SENSOR_Y = 0.4, 0.25, 10.0
A_SD, B_SD = 0.2, 0.5  # Q(x, dt) = (A + B v^2) Q_cv(dt): the noise grows with the speed v


def _speed_scale(x):
    return A_SD + B_SD * x[1] ** 2


def _sd_model(range_measurement: bool = True) -> StateSpaceModel:
    """1-D constant velocity at irregular times whose process noise depends on the speed, seen
    through the range to a sensor off the track (or its position)."""
    motion = lib.constant_velocity(1, Q_SD)
    scale = lib.noise_scaler(motion.Q, 1.0)

    def noise_at(noise, inputs, x):  # the noise depends on the state: state_dependent_noise=True
        q = scale(noise, inputs.dt)
        return q._replace(covs=q.covs * _speed_scale(x))

    def h(x, inputs):
        return jnp.hypot(x[:1], SENSOR_Y) if range_measurement else x[:1]

    return StateSpaceModel(
        f=lambda x, inputs: motion.f(x, inputs.dt),
        h=h,
        process_noise=gmm.from_gaussian(jnp.zeros(2), motion.Q(jnp.asarray(1.0))),
        measurement_noise=gmm.from_gaussian(jnp.zeros(1), R_SD * jnp.eye(1)),
        prior=gmm.from_gaussian(jnp.array([-5.0, 1.0]), jnp.diag(jnp.array([4.0, 1.0]))),
        process_noise_at=noise_at,
        call="inputs",
        state_dependent_noise=True,
    )


def _sd_data():
    rng = np.random.default_rng(5)
    times = np.cumsum(rng.uniform(0.1, 1.2, 20))
    zs = np.hypot(-5.0 + 1.5 * times, SENSOR_Y)[:, None] + rng.normal(0, 0.5, (20, 1))
    zs[6] = np.nan  # a missing measurement: predict only
    return times, zs


def _ekf_rts_np(times, zs, range_measurement=True):
    """Hand-written EKF and RTS smoother with ``Q(m_{k-1}, dt_k)`` at the mean predicted from."""
    m, P = np.array([-5.0, 1.0]), np.diag([4.0, 1.0])
    ms, Ps, Fs, Pps = [], [], [], []
    prev = 0.0
    for t, z in zip(times, zs):
        dt, prev = t - prev, t
        F = np.array([[1.0, dt], [0.0, 1.0]])
        Q = (A_SD + B_SD * m[1] ** 2) * Q_SD * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        m, P = F @ m, F @ P @ F.T + Q
        Fs.append(F), Pps.append(P)
        if not np.isnan(z).any():
            r = np.hypot(m[0], SENSOR_Y) if range_measurement else m[0]
            H = np.array([[m[0] / r, 0.0]]) if range_measurement else np.array([[1.0, 0.0]])
            S = H @ P @ H.T + R_SD
            K = P @ H.T / S
            m = m + (K * (z - r)).ravel()
            A = np.eye(2) - K @ H
            P = A @ P @ A.T + R_SD * K @ K.T
        ms.append(m), Ps.append(P)
    sm, sP = [ms[-1]], [Ps[-1]]
    for k in range(len(times) - 2, -1, -1):  # Pps[k + 1] used Q at ms[k]: the filter's own
        G = Ps[k] @ Fs[k + 1].T @ np.linalg.inv(Pps[k + 1])
        sm.insert(0, ms[k] + G @ (sm[0] - Fs[k + 1] @ ms[k]))
        sP.insert(0, Ps[k] + G @ (sP[0] - Pps[k + 1]) @ G.T)
    return np.array(ms), np.array(Ps), np.array(sm), np.array(sP)


def test_state_dependent_noise_ekf_and_rts_match_a_numpy_loop():
    times, zs = _sd_data()
    model = _sd_model()
    assert model.state_dependent_noise
    inputs = inputs_from_times(times)
    _, infos = filters.run(filters.build_ekf(model), jnp.asarray(zs), inputs)
    m, P, sm, sP = _ekf_rts_np(times, zs)
    np.testing.assert_allclose(infos.mean, m, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(infos.cov, P, rtol=1e-10, atol=1e-10)
    smooth = filters.rts_smoother(model, infos.mean, infos.cov, inputs, method="ekf")
    np.testing.assert_allclose(smooth.mean, sm, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(smooth.cov, sP, rtol=1e-9, atol=1e-9)
    # the noise does depend on the state: a constant Q(dt) gives other estimates
    const = model._replace(
        process_noise_at=lambda noise, inputs: lib.noise_scaler(lib.constant_velocity(1, Q_SD).Q, 1.0)(
            noise, inputs.dt
        ),
        state_dependent_noise=False,
    )
    other = filters.run(filters.build_ekf(const), jnp.asarray(zs), inputs)[1].mean
    assert np.abs(np.asarray(other) - m).max() > 1e-2


def test_state_dependent_noise_sigma_point_filters_use_the_mean():
    """Linear dynamics and measurement: every sigma-point filter (Q evaluated at the mean) is the
    Kalman filter of the NumPy loop, and so is an IMM of two equal modes."""
    times, zs = _sd_data()
    model = _sd_model(range_measurement=False)
    inputs = inputs_from_times(times)
    m, P, _, _ = _ekf_rts_np(times, zs, range_measurement=False)
    builds = [filters.build_kf, filters.build_ukf, filters.build_ckf, filters.build_sckf]
    builds.append(lambda mod: filters.build_imm([mod, mod], [[0.9, 0.1], [0.1, 0.9]], filter="ekf"))
    for build in builds:
        _, infos = filters.run(build(model), jnp.asarray(zs), inputs)
        np.testing.assert_allclose(infos.mean, m, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(infos.cov, P, rtol=1e-9, atol=1e-9)


def _rw_model():
    """Scalar random walk with ``v ~ N(0, 0.1 + x^2)``, ``x`` the state the step starts from."""
    return StateSpaceModel(
        f=lambda x, t: x,
        h=lambda x, t: x,
        process_noise=gmm.from_gaussian(jnp.zeros(1), jnp.eye(1)),
        measurement_noise=gmm.from_gaussian(jnp.zeros(1), jnp.eye(1)),
        prior=gmm.from_gaussian(jnp.zeros(1), jnp.eye(1)),
        process_noise_at=lambda noise, inputs, x: noise._replace(covs=noise.covs * (0.1 + x[0] ** 2)),
        state_dependent_noise=True,
    )


def test_state_dependent_noise_pf_draws_per_particle_and_simulate_follows_the_state():
    model = _rw_model()
    n = 20_000
    pf = filters.build_pf(model, n)
    x = jnp.linspace(-3.0, 3.0, n)[:, None]
    state = filters.pf.PFState(x, jnp.full((n,), -np.log(n)))
    pred = jax.jit(pf.predict)(pf.params, state, StepInputs(t=jnp.ones(())), key=jax.random.key(1))
    u = np.asarray((pred.particles - x)[:, 0] / jnp.sqrt(0.1 + x[:, 0] ** 2))  # standardised draws
    assert abs(u.mean()) < 5 / np.sqrt(n) and abs(u.var() - 1) < 5 * np.sqrt(2 / n), (u.mean(), u.var())
    # simulate draws the true noise at the true previous state
    from gmjax.models import scenario_from_model, simulate

    sc = scenario_from_model(model, 3)
    xs = jax.vmap(lambda k: simulate(sc, k)[0])(jax.random.split(jax.random.key(2), n))[..., 0]
    u = np.asarray(jnp.diff(xs, axis=1) / jnp.sqrt(0.1 + xs[:, :-1] ** 2)).ravel()
    assert abs(u.var() - 1) < 5 * np.sqrt(2 / u.size), u.var()


def test_state_dependent_noise_is_refused_clearly_where_unsupported():
    model = _rw_model()
    zs = jnp.zeros((3, 1))
    with pytest.raises(ValueError, match="depends on the state"):
        filters.run(filters.build_gsf(model, "ekf"), zs)
    with pytest.raises(ValueError, match="depends on the state"):
        model.noise_at(model.process_noise, StepInputs(t=jnp.ones(())))
