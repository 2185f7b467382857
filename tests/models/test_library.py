"""The motion/measurement model library against Stone Soup and closed forms."""

import datetime

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import mixture as gmm
from gmjax.models import library as lib

jax.config.update("jax_enable_x64", True)

DTS = [0.1, 1.0, 2.5]


def _td(dt):
    return datetime.timedelta(seconds=dt)


def _numjac(fn, x, eps=1e-6):
    cols = [
        (np.asarray(fn(jnp.asarray(x + eps * e))) - np.asarray(fn(jnp.asarray(x - eps * e)))) / (2 * eps)
        for e in np.eye(len(x))
    ]
    return np.stack(cols, axis=1)


def _ss(model, x):
    from stonesoup.types.state import State

    return np.asarray(model.function(State(x.reshape(-1, 1))), float).ravel()


@pytest.mark.parametrize("dt", DTS)
def test_nth_derivative_matches_stonesoup(dt):
    lin = pytest.importorskip("stonesoup.models.transition.linear")
    for order, ndim, q in [(1, 2, (0.3, 2.0)), (2, 3, 0.7), (3, 1, 1.5)]:
        ours = lib.nth_derivative(order, ndim, q)
        qs = np.broadcast_to(np.asarray(q, float), (ndim,))
        ss = lin.CombinedLinearGaussianTransitionModel(
            [lin.ConstantNthDerivative(constant_derivative=order, noise_diff_coeff=float(qa)) for qa in qs]
        )
        np.testing.assert_allclose(ours.F(jnp.asarray(dt)), ss.matrix(time_interval=_td(dt)), atol=1e-12)
        np.testing.assert_allclose(
            ours.Q(jnp.asarray(dt)), ss.covar(time_interval=_td(dt)), rtol=1e-10, atol=1e-14
        )


@pytest.mark.parametrize("dt", DTS)
def test_cv_ca_rw_match_stonesoup(dt):
    lin = pytest.importorskip("stonesoup.models.transition.linear")
    cv = lib.constant_velocity(2, 0.5)
    ss = lin.CombinedLinearGaussianTransitionModel([lin.ConstantVelocity(0.5)] * 2)
    np.testing.assert_allclose(cv.Q(dt), ss.covar(time_interval=_td(dt)), rtol=1e-12)
    np.testing.assert_allclose(cv.F(dt), ss.matrix(time_interval=_td(dt)), rtol=1e-12)
    ca = lib.constant_acceleration(1, 0.2)
    ssa = lin.ConstantAcceleration(0.2)
    np.testing.assert_allclose(ca.Q(dt), ssa.covar(time_interval=_td(dt)), rtol=1e-12)
    rw = lib.random_walk(3, 0.4)
    ssr = lin.CombinedLinearGaussianTransitionModel([lin.RandomWalk(0.4)] * 3)
    np.testing.assert_allclose(rw.Q(dt), ssr.covar(time_interval=_td(dt)), rtol=1e-12)
    np.testing.assert_allclose(rw.F(dt), ssr.matrix(time_interval=_td(dt)), rtol=1e-12)


@pytest.mark.parametrize("dt", DTS)
def test_singer_matches_stonesoup_and_van_loan(dt):
    lin = pytest.importorskip("stonesoup.models.transition.linear")
    from scipy.linalg import expm

    q, alpha = 0.8, 0.3
    ours = lib.singer(1, q, alpha)
    ss = lin.Singer(noise_diff_coeff=q, damping_coeff=alpha)
    np.testing.assert_allclose(ours.F(dt), ss.matrix(time_interval=_td(dt)), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(ours.Q(dt), ss.covar(time_interval=_td(dt)), rtol=1e-7, atol=1e-12)
    # Van Loan's method: the exact discretisation of dx = A x dt + L dW
    A = np.array([[0, 1, 0], [0, 0, 1], [0, 0, -alpha]])
    Lq = np.diag([0, 0, q])
    M = expm(np.block([[-A, Lq], [np.zeros((3, 3)), A.T]]) * dt)
    Fd = M[3:, 3:].T
    np.testing.assert_allclose(ours.F(dt), Fd, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(ours.Q(dt), Fd @ M[:3, 3:], rtol=1e-7, atol=1e-12)


@pytest.mark.parametrize("dt", DTS)
def test_turn_models_match_stonesoup(dt):
    lin = pytest.importorskip("stonesoup.models.transition.linear")
    nl = pytest.importorskip("stonesoup.models.transition.nonlinear")
    from stonesoup.types.state import State

    ct = lib.coordinated_turn(0.2, (0.3, 0.6))
    ss = lin.KnownTurnRate(turn_noise_diff_coeffs=(0.3, 0.6), turn_rate=0.2)
    np.testing.assert_allclose(ct.F(dt), ss.matrix(time_interval=_td(dt)), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(ct.Q(dt), ss.covar(time_interval=_td(dt)), rtol=1e-12)
    ctu = lib.coordinated_turn_unknown_rate((0.3, 0.6), 0.01)
    ssu = nl.ConstantTurn(linear_noise_coeffs=np.array([0.3, 0.6]), turn_noise_coeff=0.01)
    x = np.array([10.0, 3.0, -4.0, 1.5, 0.15])
    want = ssu.function(State(x.reshape(-1, 1)), time_interval=_td(dt)).ravel()
    np.testing.assert_allclose(ctu.f(jnp.asarray(x), dt), want, rtol=1e-12)
    np.testing.assert_allclose(ctu.Q(dt), ssu.covar(time_interval=_td(dt)), rtol=1e-12)
    # Jacobian from JAX against central differences
    J = ctu.jacobian(jnp.asarray(x), dt)
    eps = 1e-6
    num = _numjac(lambda y: ctu.f(y, dt), x, eps)
    np.testing.assert_allclose(J, num, rtol=1e-6, atol=1e-8)


def test_measurement_models_match_stonesoup():
    nlm = pytest.importorskip("stonesoup.models.measurement.nonlinear")

    x4 = np.array([-30.0, 2.0, 40.0, -1.0])
    br = lib.bearing_range((0, 2), (0.01, 2.0))
    ss = nlm.CartesianToBearingRange(ndim_state=4, mapping=(0, 2), noise_covar=np.diag([1e-4, 4.0]))
    np.testing.assert_allclose(br.h(jnp.asarray(x4)), _ss(ss, x4), rtol=1e-12)
    np.testing.assert_allclose(br.R, ss.covar(), rtol=1e-12)
    assert br.angle_dims == (0,)
    x6 = np.array([-30.0, 2.0, 40.0, -1.0, 12.0, 0.3])
    ebr = lib.elevation_bearing_range((0, 2, 4))
    sse = nlm.CartesianToElevationBearingRange(ndim_state=6, mapping=(0, 2, 4), noise_covar=np.eye(3))
    np.testing.assert_allclose(ebr.h(jnp.asarray(x6)), _ss(sse, x6), rtol=1e-12)
    bo = lib.bearings_only((0, 2))
    ssb = nlm.Cartesian2DToBearing(ndim_state=4, mapping=(0, 2), noise_covar=np.eye(1))
    np.testing.assert_allclose(bo.h(jnp.asarray(x4)), _ss(ssb, x4), rtol=1e-12)
    # range rate: closed form, and the Jacobian from JAX against finite differences
    brr = lib.bearing_range_rate()
    z = np.asarray(brr.h(jnp.asarray(x4)))
    p, v = x4[[0, 2]], x4[[1, 3]]
    np.testing.assert_allclose(z[2], p @ v / np.linalg.norm(p), rtol=1e-12)
    J = np.asarray(brr.jacobian(jnp.asarray(x4)))
    num = _numjac(brr.h, x4)
    np.testing.assert_allclose(J, num, rtol=1e-6, atol=1e-9)


def test_cartesian_position_and_glint():
    cp = lib.cartesian_position((0, 2), 4, (1.0, 2.0))
    np.testing.assert_allclose(cp.H, [[1, 0, 0, 0], [0, 0, 1, 0]])
    np.testing.assert_allclose(cp.R, np.diag([1.0, 4.0]))
    g = lib.glint_mixture(np.eye(2), 0.1, 5.0)
    _, cov = gmm.moments(g)
    np.testing.assert_allclose(cov, (0.9 + 0.1 * 25) * np.eye(2), rtol=1e-12)


def test_noise_scaler_maps_reference_noise_to_q_dt():
    cv = lib.constant_velocity(2, 0.7)
    q1 = gmm.from_gaussian(jnp.zeros(4), cv.Q(jnp.asarray(1.0)))
    scale = lib.noise_scaler(cv.Q, 1.0)
    for dt in DTS:
        out = scale(q1, jnp.asarray(dt))
        np.testing.assert_allclose(out.covs[0], cv.Q(jnp.asarray(dt)), rtol=1e-10, atol=1e-14)


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="q"):
        lib.constant_velocity(2, -1.0)
    with pytest.raises(ValueError, match="q"):
        lib.constant_velocity(2, (1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match="alpha"):
        lib.singer(1, 1.0, 0.0)
    with pytest.raises(ValueError, match="position_dims"):
        lib.bearing_range((0, 0))
    with pytest.raises(ValueError, match="R"):
        lib.bearing_range((0, 2), np.eye(3))
    with pytest.raises(ValueError, match="order"):
        lib.nth_derivative(0)
