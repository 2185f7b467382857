"""Paper scenarios rebuilt from gmjax.models.library pieces give the numbers of their former
hand-written construction (rebuilt here, as it was)."""

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import filters, reduction
from gmjax.mixture import GaussianMixture
from gmjax.models import StateSpaceModel, simulate
from gmjax.scenarios import uwb_velocity
from gmjax.scenarios.bearings_only import BEARINGS_PROCESS_NOISE, BEARINGS_SENSORS, bearings_only

jax.config.update("jax_enable_x64", True)


def _old_bearings_model(dt=0.01, bearing_std=0.1, dtype=jnp.float64):
    """The hand-written model of seed 001 §4.2 as ``bearings_only`` built it before the library."""
    I2 = np.eye(2)
    A = np.block([[I2, dt * I2], [np.zeros((2, 2)), I2]])
    Q1 = np.block([[dt**3 / 3 * I2, dt**2 / 2 * I2], [dt**2 / 2 * I2, dt * I2]])
    g = np.array([dt**2 / 2, dt**2 / 2, dt, dt])
    qw, qmu, qvar = BEARINGS_PROCESS_NOISE
    q = GaussianMixture.create(qw, [m * g for m in qmu], [v * Q1 for v in qvar], dtype=dtype)
    r = GaussianMixture.create([1.0], [[0.0, 0.0]], [bearing_std**2 * np.eye(2)], dtype=dtype)
    prior = GaussianMixture.create([1.0], [np.zeros(4)], [np.diag([0.1, 0.1, 10.0, 10.0])], dtype=dtype)
    A_j = jnp.asarray(A, dtype)
    sensors = jnp.asarray(BEARINGS_SENSORS, dtype)
    return StateSpaceModel(
        f=lambda x, t: A_j @ x,
        h=lambda x, t: jnp.arctan2(x[1] - sensors[:, 1], x[0] - sensors[:, 0]),
        process_noise=q,
        measurement_noise=r,
        prior=prior,
    )


def test_bearings_only_from_the_library_equals_the_former_construction():
    sc = bearings_only(n_steps=120)
    old = _old_bearings_model()
    new = sc.model
    assert new.angle_dims == () and new.call == "t"
    np.testing.assert_array_equal(new.process_noise.means, old.process_noise.means)
    np.testing.assert_allclose(new.process_noise.covs, old.process_noise.covs, rtol=1e-15, atol=0)
    for leaf_new, leaf_old in zip(new.measurement_noise, old.measurement_noise):
        np.testing.assert_array_equal(leaf_new, leaf_old)
    xs = jax.random.normal(jax.random.key(0), (50, 4))
    for fn in ("f", "h"):
        a = jax.vmap(lambda x, fn=fn: getattr(new, fn)(x, 1))(xs)
        b = jax.vmap(lambda x, fn=fn: getattr(old, fn)(x, 1))(xs)
        np.testing.assert_array_equal(a, b)
    # the simulation (truth and measurements) is bit-identical
    sim_new = simulate(sc, jax.random.key(3))
    sim_old = simulate(sc._replace(model=old), jax.random.key(3))
    for a, b in zip(sim_new[:2], sim_old[:2]):
        np.testing.assert_array_equal(a, b)
    # a Gaussian sum CKF (as seed 001 runs) agrees to rounding (Q_1 = q dt^3 / 3 differs in the last bit)
    gsf = lambda m: filters.build_gsf(m, "ckf", reduction.Runnalls(num_out=3), 3, track_ise=False)  # noqa: E731
    a = filters.run(gsf(new), sim_new[1], sim_new[2])[1]
    b = filters.run(gsf(old), sim_new[1], sim_new[2])[1]
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-12, atol=1e-14)


def test_uwb_velocity_from_the_library_is_bit_identical():
    dt = uwb_velocity.DT
    F_old = np.array([[1.0, dt], [0.0, 1.0]])
    H_old = np.array([[1.0, 0.0]])
    noise = uwb_velocity.UWB_NOISES["x"]
    sc = uwb_velocity.random_walk_velocity(noise["process"], noise["measurement"], n_steps=40)
    model = uwb_velocity.rwv_model(noise["process"], noise["measurement"])
    x = jnp.array([1.5, -0.7])
    for m in (sc.model, model):
        np.testing.assert_array_equal(m.f_jacobian(x, 1), F_old)
        np.testing.assert_array_equal(m.h_jacobian(x, 1), H_old)
        np.testing.assert_array_equal(m.f(x, 1), jnp.asarray(F_old) @ x)
    old = sc.model._replace(
        f=lambda x, t: jnp.asarray(F_old) @ x,
        h=lambda x, t: jnp.asarray(H_old) @ x,
        f_jacobian=lambda x, t: jnp.asarray(F_old),
        h_jacobian=lambda x, t: jnp.asarray(H_old),
    )
    sim_new = simulate(sc, jax.random.key(1))
    sim_old = simulate(sc._replace(model=old), jax.random.key(1))
    for a, b in zip(sim_new[:2], sim_old[:2]):
        np.testing.assert_array_equal(a, b)
    labeled = uwb_velocity.simulate_labeled(
        noise["process"], noise["measurement"], jax.random.key(2), n_steps=30
    )
    truth = np.asarray(labeled.xs)
    increments = truth[1:] - truth[:-1] @ F_old.T  # v_k = s_k (dt, 1): the rank-one noise of eq 20
    np.testing.assert_allclose(increments[:, 0], dt * increments[:, 1], rtol=1e-9, atol=1e-12)
    a = filters.run(filters.build_kf(sc.model), sim_new[1])[1]
    b = filters.run(filters.build_kf(old), sim_new[1])[1]
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.cov, b.cov)
