"""Gaussian local filters: FilterPy agreement (KF, EKF, UKF, CKF), SCKF == CKF, every filter == KF
on a linear-Gaussian model, noise means, NaN measurements, repair flags, jit/vmap/dtypes/padding,
and bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import filters as F
from gmjax import mixture as gmm
from gmjax.mixture import GaussianMixture as GM
from gmjax.models import StateSpaceModel

T = 100
SENSOR = (-20.0, -30.0)
Q = np.diag([0.02, 0.01, 0.02, 0.01])
R = np.diag([0.5**2, 0.02**2])
X0 = np.array([0.0, 1.0, 0.0, 0.5])
P0 = np.diag([4.0, 0.5, 4.0, 0.5])


# ---- a nonlinear 4-D model written once for NumPy (FilterPy) and JAX ----------------------------
def f_xp(x, xp):
    px, vx, py, vy = x[0], x[1], x[2], x[3]
    return xp.stack([px + vx, vx + 0.1 * xp.sin(py / 5.0), py + vy, vy + 0.1 * xp.cos(px / 5.0)])


def h_xp(x, xp):
    dx, dy = x[0] - SENSOR[0], x[2] - SENSOR[1]
    return xp.stack([xp.sqrt(dx * dx + dy * dy), xp.arctan2(dy, dx)])


def f_jax(x, t):
    return f_xp(x, jnp)


def h_jax(x, t):
    return h_xp(x, jnp)


def simulate(seed=0, steps=T):
    rng = np.random.default_rng(seed)
    x = X0 + rng.multivariate_normal(np.zeros(4), P0)
    zs = []
    for _ in range(steps):
        x = f_xp(x, np) + rng.multivariate_normal(np.zeros(4), Q)
        zs.append(h_xp(x, np) + rng.multivariate_normal(np.zeros(2), R))
    return np.array(zs)


def nonlinear_model(dtype=jnp.float64, capacity=None):
    return StateSpaceModel(
        f_jax,
        h_jax,
        GM.create([1.0], [np.zeros(4)], [Q], capacity=capacity, dtype=dtype),
        GM.create([1.0], [np.zeros(2)], [R], capacity=capacity, dtype=dtype),
        GM.create([1.0], [X0], [P0], capacity=capacity, dtype=dtype),
    )


# ---- a linear-Gaussian model -------------------------------------------------------------------
A_LIN = np.array([[1.0, 1.0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 1.0], [0, 0, 0, 1.0]])
H_LIN = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
R_LIN = np.diag([1.0, 0.5])


def linear_model(dtype=jnp.float64, capacity=None):
    A, H = jnp.asarray(A_LIN, dtype), jnp.asarray(H_LIN, dtype)
    return StateSpaceModel(
        lambda x, t: A @ x,
        lambda x, t: H @ x,
        GM.create([1.0], [np.zeros(4)], [Q], capacity=capacity, dtype=dtype),
        GM.create([1.0], [np.zeros(2)], [R_LIN], capacity=capacity, dtype=dtype),
        GM.create([1.0], [X0], [P0], capacity=capacity, dtype=dtype),
    )


def linear_data(seed=1, steps=T):
    rng = np.random.default_rng(seed)
    x = X0.copy()
    zs = []
    for _ in range(steps):
        x = A_LIN @ x + rng.multivariate_normal(np.zeros(4), Q)
        zs.append(H_LIN @ x + rng.multivariate_normal(np.zeros(2), R_LIN))
    return np.array(zs)


_RUNNERS = {}


def runner(name, model_fn=None, **model_kw):
    """A jitted ``run`` of builder ``name`` on a model, compiled once per test session."""
    key = (name, model_fn, tuple(sorted(model_kw.items())))
    if key not in _RUNNERS:
        model = (model_fn or nonlinear_model)(**model_kw)
        flt = ALL_BUILDERS[name](model)
        _RUNNERS[key] = (flt, jax.jit(lambda z: F.run(flt, z)))
    return _RUNNERS[key]


def _assert_states(states, xs, Ps, lls, infos, tol=1e-8):
    np.testing.assert_allclose(np.asarray(states.mean), xs, rtol=tol, atol=tol)
    np.testing.assert_allclose(np.asarray(states.cov), Ps, rtol=tol, atol=tol)
    np.testing.assert_allclose(np.asarray(infos.loglik), lls, rtol=tol, atol=tol)


# ---- FilterPy agreement (float64, 100 steps) ---------------------------------------------------
def test_kf_matches_filterpy():
    from filterpy.kalman import KalmanFilter

    zs = linear_data()
    kf = KalmanFilter(4, 2)
    kf.x, kf.P, kf.F, kf.H, kf.Q, kf.R = X0.copy(), P0.copy(), A_LIN, H_LIN, Q, R_LIN
    xs, Ps, lls, ys = [], [], [], []
    for z in zs:
        kf.predict()
        kf.update(z)
        xs.append(kf.x.copy()), Ps.append(kf.P.copy()), lls.append(kf.log_likelihood)
        ys.append(kf.y.copy())
    states, infos = runner("kf", linear_model)[1](jnp.asarray(zs))
    _assert_states(states, np.array(xs), np.array(Ps), np.array(lls), infos)
    np.testing.assert_allclose(np.asarray(infos.extra["innovation"]), np.array(ys), rtol=1e-8, atol=1e-8)
    # local_kf with explicit matrices is the same filter
    loc = F.local_kf(A_LIN, H_LIN)
    s2, i2 = jax.jit(lambda z: F.run(F.from_local(linear_model(), loc), z))(jnp.asarray(zs))
    np.testing.assert_allclose(np.asarray(s2.mean), np.array(xs), rtol=1e-8, atol=1e-8)


def test_ekf_matches_filterpy():
    from filterpy.kalman import ExtendedKalmanFilter

    zs = simulate()
    jf = jax.jit(jax.jacfwd(f_jax))
    jh = jax.jit(jax.jacfwd(h_jax))

    class EKF(ExtendedKalmanFilter):
        def predict_x(self, u=0):
            self.x = f_xp(self.x, np)

    ekf = EKF(4, 2)
    ekf.x, ekf.P, ekf.Q, ekf.R = X0.copy(), P0.copy(), Q, R
    xs, Ps, lls = [], [], []
    for z in zs:
        ekf.F = np.asarray(jf(jnp.asarray(ekf.x), 0))
        ekf.predict()
        ekf.update(z, lambda x: np.asarray(jh(jnp.asarray(x), 0)), lambda x: h_xp(x, np))
        xs.append(ekf.x.copy()), Ps.append(ekf.P.copy()), lls.append(ekf.log_likelihood)
    states, infos = runner("ekf")[1](jnp.asarray(zs))
    _assert_states(states, np.array(xs), np.array(Ps), np.array(lls), infos)


def test_ukf_matches_filterpy_merwe():
    """FilterPy reuses f(X_i) in the update; the papers (and gmjax) redraw the points from the
    predicted Gaussian (seed 001 eq 13), so we redraw in FilterPy too (sigmas_f after predict)."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    zs = simulate()
    alpha, beta, kappa = 0.5, 2.0, -1.0
    pts = MerweScaledSigmaPoints(4, alpha=alpha, beta=beta, kappa=kappa)
    ukf = UnscentedKalmanFilter(4, 2, 1.0, lambda x: h_xp(x, np), lambda x, dt: f_xp(x, np), pts)
    ukf.x, ukf.P, ukf.Q, ukf.R = X0.copy(), P0.copy(), Q, R
    xs, Ps, lls = [], [], []
    for z in zs:
        ukf.predict()
        ukf.sigmas_f = pts.sigma_points(ukf.x, ukf.P)
        ukf.update(z)
        xs.append(ukf.x.copy()), Ps.append(ukf.P.copy()), lls.append(ukf.log_likelihood)
    ours = F.build_ukf(nonlinear_model(), alpha, beta, kappa)
    states, infos = jax.jit(lambda z: F.run(ours, z))(jnp.asarray(zs))
    _assert_states(states, np.array(xs), np.array(Ps), np.array(lls), infos)


def test_ckf_matches_filterpy():
    from filterpy.kalman import CubatureKalmanFilter, spherical_radial_sigmas

    zs = simulate()
    ckf = CubatureKalmanFilter(4, 2, 1.0, lambda x: h_xp(x, np), lambda x, dt: f_xp(x, np))
    # FilterPy's CKF keeps column vectors: x (4, 1), z (2, 1)
    ckf.x, ckf.P, ckf.Q, ckf.R = X0.copy()[:, None], P0.copy(), Q, R
    xs, Ps, lls = [], [], []
    for z in zs:
        ckf.predict()
        ckf.sigmas_f = spherical_radial_sigmas(ckf.x, ckf.P)  # redraw, as seed 001 eq 13
        ckf.update(z[:, None])
        xs.append(ckf.x.ravel().copy()), Ps.append(ckf.P.copy()), lls.append(ckf.log_likelihood)
    states, infos = runner("ckf")[1](jnp.asarray(zs))
    _assert_states(states, np.array(xs), np.array(Ps), np.array(lls), infos)


# ---- internal consistency ----------------------------------------------------------------------
def test_sckf_equals_ckf():
    zs = jnp.asarray(simulate(3))
    s1, i1 = runner("ckf")[1](zs)
    sq, run_sq = runner("sckf")
    s2, i2 = run_sq(zs)
    m2, P2 = i2.mean, i2.cov
    np.testing.assert_allclose(np.asarray(m2), np.asarray(s1.mean), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(P2), np.asarray(s1.cov), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(i2.loglik), np.asarray(i1.loglik), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(
        np.asarray(i2.extra["innovation_cov"]), np.asarray(i1.extra["innovation_cov"]), rtol=1e-9, atol=1e-9
    )
    # the carried factor is lower triangular with a non-negative diagonal
    chol = np.asarray(s2.chol)
    assert np.allclose(np.triu(chol, 1), 0.0)
    assert np.all(np.diagonal(chol, axis1=1, axis2=2) >= 0)


def test_tria_reproduces_gram_matrix():
    A = jnp.asarray(np.random.default_rng(0).normal(size=(3, 7)))
    S = F.tria(A)
    np.testing.assert_allclose(np.asarray(S @ S.T), np.asarray(A @ A.T), rtol=1e-12, atol=1e-12)
    assert np.allclose(np.triu(np.asarray(S), 1), 0.0)


ALL_BUILDERS = {
    "kf": F.build_kf,
    "ekf": F.build_ekf,
    "ukf": lambda m: F.build_ukf(m),
    "ukf_merwe": lambda m: F.build_ukf(m, 1e-3, 2.0, 0.0),
    "ckf": F.build_ckf,
    "ghkf": lambda m: F.build_ghkf(m, 3),
    "sgkf": lambda m: F.build_sgkf(m, 2),
    "sgkf3": lambda m: F.build_sgkf(m, 3, "exponential"),
    "sckf": F.build_sckf,
}


_SLOW_LINEAR = {"ghkf", "sgkf3", "ukf_merwe", "ckf", "ekf"}


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(n, marks=pytest.mark.slow) if n in _SLOW_LINEAR else n
        for n in sorted(ALL_BUILDERS)
        if n != "kf"
    ],
)
def test_every_filter_equals_kf_on_linear_gaussian(name):
    zs = jnp.asarray(linear_data(2, 50))
    ref, rinfo = runner("kf", linear_model)[1](zs)
    flt, run_ = runner(name, linear_model)
    st, info = run_(zs)
    mean, cov = info.mean, info.cov
    tol = 1e-6 if name == "ukf_merwe" else 1e-9  # alpha = 1e-3 has weights ~1e6: cancellation
    np.testing.assert_allclose(np.asarray(mean), np.asarray(ref.mean), rtol=tol, atol=tol)
    np.testing.assert_allclose(np.asarray(cov), np.asarray(ref.cov), rtol=tol, atol=tol)
    np.testing.assert_allclose(np.asarray(info.loglik), np.asarray(rinfo.loglik), rtol=tol, atol=tol)


LOCALS = {
    "kf": lambda: F.local_kf(A_LIN, H_LIN),
    "ekf": lambda: F.local_ekf(lambda x, t: jnp.asarray(A_LIN) @ x, lambda x, t: jnp.asarray(H_LIN) @ x),
    "ckf": lambda: F.local_ckf(lambda x, t: jnp.asarray(A_LIN) @ x, lambda x, t: jnp.asarray(H_LIN) @ x),
    "sckf": lambda: F.local_sckf(lambda x, t: jnp.asarray(A_LIN) @ x, lambda x, t: jnp.asarray(H_LIN) @ x),
}


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n == "ekf" else n for n in sorted(LOCALS)]
)
def test_noise_means_are_shifts(name):
    """x' = f(x) + v with E v = q equals the zero-mean filter on f(x) + q (and likewise for h)."""
    loc = LOCALS[name]()
    q_mean = jnp.array([0.3, -0.1, 0.2, 0.05])
    r_mean = jnp.array([1.0, -2.0])
    z = jnp.array([3.0, 1.0])

    @jax.jit
    def with_means():
        st = loc.init(jnp.asarray(X0), jnp.asarray(P0))
        a = loc.predict(st, 1, q_mean, jnp.asarray(Q))
        a, ia = loc.update(a, z, 1, r_mean, jnp.asarray(R_LIN))
        return loc.moments(a), ia

    shifted = F.local_ekf(
        lambda x, t: jnp.asarray(A_LIN) @ x + q_mean, lambda x, t: jnp.asarray(H_LIN) @ x + r_mean
    )

    @jax.jit
    def shifted_fns():
        b = shifted.init(jnp.asarray(X0), jnp.asarray(P0))
        b = shifted.predict(b, 1, jnp.zeros(4), jnp.asarray(Q))
        return shifted.update(b, z, 1, jnp.zeros(2), jnp.asarray(R_LIN))

    (ma, Pa), ia = with_means()
    b, ib = shifted_fns()
    np.testing.assert_allclose(np.asarray(ma), np.asarray(b.mean), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(Pa), np.asarray(b.cov), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(float(ia.loglik), float(ib.loglik), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(ia.innovation), np.asarray(ib.innovation), atol=1e-10)


def test_gm_noise_and_prior_are_moment_matched():
    """A 2-component noise GM gives the filter of its moment-matched Gaussian."""
    model = linear_model()
    q_gm = GM.create([0.3, 0.7], [np.full(4, 0.5), np.full(4, -0.2)], [Q, 2 * Q])
    r_gm = GM.create([0.5, 0.5], [[1.0, 0.0], [-1.0, 0.0]], [R_LIN, R_LIN], capacity=4)
    gm_model = model._replace(process_noise=q_gm, measurement_noise=r_gm)
    qm, qc = gmm.moments(q_gm)
    rm, rc = gmm.moments(r_gm)
    mm_model = model._replace(
        process_noise=GM.create([1.0], [np.asarray(qm)], [np.asarray(qc)]),
        measurement_noise=GM.create([1.0], [np.asarray(rm)], [np.asarray(rc)]),
    )
    zs = jnp.asarray(linear_data(4, 20))
    a, _ = jax.jit(lambda z: F.run(F.build_ekf(gm_model), z))(zs)
    b, _ = jax.jit(lambda z: F.run(F.build_ekf(mm_model), z))(zs)
    np.testing.assert_allclose(np.asarray(a.mean), np.asarray(b.mean), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "name", ["sckf", pytest.param("ekf", marks=pytest.mark.slow), pytest.param("ukf", marks=pytest.mark.slow)]
)
def test_padded_slots_do_not_change_results(name):
    zs = jnp.asarray(simulate(5, T))
    a, ia = runner(name)[1](zs)
    b, ib = runner(name, capacity=3)[1](zs)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(np.asarray(ia.loglik), np.asarray(ib.loglik), rtol=1e-13)


# ---- NaN measurements, repair ------------------------------------------------------------------
@pytest.mark.parametrize(
    "name", ["ckf", pytest.param("ekf", marks=pytest.mark.slow), pytest.param("sckf", marks=pytest.mark.slow)]
)
def test_nan_measurement_is_predict_only(name):
    flt, run_ = runner(name)
    zs = np.asarray(simulate(6, T))
    zs_nan = zs.copy()
    zs_nan[4, 1] = np.nan
    states, infos = run_(jnp.asarray(zs_nan))
    # step 4: the posterior equals the prediction from step 3
    s3 = jax.tree_util.tree_map(lambda a: a[3], states)
    pred = jax.jit(lambda s: flt.predict(flt.params, s, F.StepInputs(t=jnp.int32(5))))(s3)
    s4 = jax.tree_util.tree_map(lambda a: a[4], states)
    for x, y in zip(jax.tree_util.tree_leaves(s4), jax.tree_util.tree_leaves(pred)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-14, atol=1e-14)
    assert float(infos.loglik[4]) == 0.0
    assert np.all(np.asarray(infos.extra["innovation"][4]) == 0.0)
    assert np.all(np.isfinite(np.asarray(infos.loglik)))
    # gradients of the total log-likelihood w.r.t. the measurements stay finite (0 at the NaN)
    g = jax.jit(jax.grad(lambda z: jnp.sum(run_(z)[1].loglik)))(jnp.asarray(zs_nan))
    assert np.all(np.isfinite(np.asarray(g)))
    assert np.all(np.asarray(g[4]) == 0.0)


@pytest.mark.parametrize(
    "name",
    ["kf", "sckf", pytest.param("ekf", marks=pytest.mark.slow), pytest.param("ckf", marks=pytest.mark.slow)],
)
def test_indefinite_covariance_is_repaired_and_flagged(name):
    loc = LOCALS[name]()
    bad_R = jnp.array([[1.0, 0.0], [0.0, -50.0]])  # makes S indefinite
    st = loc.init(jnp.asarray(X0), jnp.asarray(P0))
    upd = jax.jit(lambda s, R_: loc.update(s, jnp.array([1.0, 2.0]), 1, jnp.zeros(2), R_))
    new, info = upd(st, bad_R)
    assert bool(info.repaired)
    for leaf in jax.tree_util.tree_leaves(new) + [info.loglik]:
        assert np.all(np.isfinite(np.asarray(leaf)))
    _, cov = loc.moments(new)
    assert np.linalg.eigvalsh(np.asarray(cov)).min() > 0
    # and a healthy update is not flagged
    _, ok = upd(st, jnp.asarray(R_LIN))
    assert not bool(ok.repaired)


def test_sigma_filter_with_indefinite_prior_flags_repair():
    loc = F.local_ckf(lambda x, t: x, lambda x, t: x[:2])
    bad = F.GaussianState(jnp.zeros(4), jnp.diag(jnp.array([1.0, 1.0, -1e-3, 1.0])))
    new, info = jax.jit(loc.update)(bad, jnp.zeros(2), 0, jnp.zeros(2), jnp.eye(2))
    assert bool(info.repaired)
    assert np.all(np.isfinite(np.asarray(new.cov)))


# ---- jit / vmap / dtypes -----------------------------------------------------------------------
@pytest.mark.parametrize(
    "name", ["ckf", pytest.param("sckf", marks=pytest.mark.slow), pytest.param("ekf", marks=pytest.mark.slow)]
)
def test_jit_equals_eager_and_vmap_equals_loop(name):
    flt, jitted = runner(name)
    zs = jnp.asarray(np.stack([simulate(s, T) for s in range(3)]))
    eager = F.run(flt, zs[0])
    batched = jax.jit(jax.vmap(jitted))(zs)
    for x, y in zip(jax.tree_util.tree_leaves(eager), jax.tree_util.tree_leaves(jitted(zs[0]))):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-12, atol=1e-12)
    for i in range(3):
        loop_i = jitted(zs[i])
        for x, y in zip(
            jax.tree_util.tree_leaves(loop_i),
            jax.tree_util.tree_leaves(jax.tree_util.tree_map(lambda a: a[i], batched)),
        ):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "name", ["sckf"] + [pytest.param(n, marks=pytest.mark.slow) for n in ("ukf", "ekf", "ckf", "sgkf")]
)
def test_float32_tracks_float64(name):
    zs = simulate(7, T)
    flt64, run64 = runner(name)
    flt32, run32 = runner(name, dtype=jnp.float32)
    s64, i64 = run64(jnp.asarray(zs, jnp.float64))
    s32, i32 = run32(jnp.asarray(zs, jnp.float32))
    m64, m32 = i64.mean, i32.mean
    assert m32.dtype == jnp.float32 and i32.loglik.dtype == jnp.float32
    sd = np.sqrt(np.diagonal(np.asarray(i64.cov), axis1=1, axis2=2))
    # float32 rounding moves the estimate by a tiny fraction of its own standard deviation
    assert np.max(np.abs(np.asarray(m32) - np.asarray(m64)) / sd) < 1e-2
    assert not np.any(np.asarray(i32.flags.repaired))


# ---- bad input ---------------------------------------------------------------------------------
def test_bad_input_raises():
    model = nonlinear_model()
    with pytest.raises(ValueError, match="model.h"):
        F.build_ckf(model._replace(h=lambda x, t: x[:3]))
    with pytest.raises(ValueError, match="model.f"):
        F.build_ekf(model._replace(f=lambda x, t: x[:3]))
    with pytest.raises(ValueError, match="process_noise"):
        F.build_kf(model._replace(process_noise=GM.create([1.0], [np.zeros(3)], [np.eye(3)])))
    not_pd = GM(jnp.ones(1), jnp.zeros((1, 2)), jnp.array([[[1.0, 0.0], [0.0, -1.0]]]), jnp.ones(1, bool))
    with pytest.raises(ValueError, match="measurement_noise.*positive definite"):
        F.build_ukf(model._replace(measurement_noise=not_pd))
    with pytest.raises(ValueError, match="alpha"):
        F.build_ukf(model, alpha=0.0)
    with pytest.raises(ValueError, match="kappa"):
        F.build_ukf(model, alpha=1.0, kappa=-5.0)
    with pytest.raises(ValueError, match="order"):
        F.local_ghkf(f_jax, h_jax, order=0)
    with pytest.raises(ValueError, match="growth"):
        F.build_sgkf(model, 2, "fast")
    with pytest.raises(ValueError, match="F:"):
        F.local_kf(np.ones((2, 3)), np.ones((1, 2)))
    with pytest.raises(ValueError, match="H:"):
        F.local_kf(np.eye(2), np.ones((1, 3)))
    with pytest.raises(ValueError, match="zs"):
        F.run(F.build_ckf(model), jnp.zeros(5))
    with pytest.raises(ValueError, match="inputs.t"):
        F.run(F.build_ckf(model), jnp.zeros((5, 2)), jnp.arange(4))


def test_safe_chol_repairs_flags_and_matches_numpy():
    from gmjax.filters._core import safe_chol

    rng = np.random.default_rng(0)
    B = rng.normal(size=(4, 4))
    P = B @ B.T + np.eye(4)
    bad = np.diag([1.0, 2.0, -0.5, 1e-3]) + 0.1 * np.ones((4, 4))
    run = jax.jit(safe_chol)
    good = run(jnp.asarray(P))
    np.testing.assert_allclose(np.asarray(good.factor), np.linalg.cholesky(P), rtol=1e-12)
    assert not bool(good.repaired) and float(good.jitter) == 0.0
    fixed = run(jnp.asarray(bad))
    L = np.asarray(fixed.factor)
    assert bool(fixed.repaired) and np.all(np.isfinite(L))
    # the repair is symmetrise + jitter on the diagonal, and the result is PD
    np.testing.assert_allclose(L @ L.T, bad + float(fixed.jitter) * np.eye(4), rtol=1e-10, atol=1e-10)
    assert float(fixed.jitter) > 0.5  # at least the negative eigenvalue's size
    g = jax.jit(jax.grad(lambda A: jnp.sum(safe_chol(A).factor)))(jnp.asarray(bad))
    assert np.all(np.isfinite(np.asarray(g)))


# ---- parameters are data -----------------------------------------------------------------------
def test_kalman_filter_from_arrays_equals_model_kf_and_filterpy_loglik():
    from filterpy.kalman import KalmanFilter

    zs = linear_data(2, 30)
    kf_arrays = F.kalman_filter(A_LIN, H_LIN, Q, R_LIN, X0, P0)
    s1, i1 = jax.jit(lambda z: F.run(kf_arrays, z))(jnp.asarray(zs))
    s2, i2 = runner("kf", linear_model)[1](jnp.asarray(zs))
    np.testing.assert_allclose(np.asarray(s1.mean), np.asarray(s2.mean), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(i1.loglik), np.asarray(i2.loglik), rtol=1e-12, atol=1e-12)
    ref = KalmanFilter(4, 2)
    ref.x, ref.P, ref.F, ref.H, ref.Q, ref.R = X0.copy(), P0.copy(), A_LIN, H_LIN, Q, R_LIN
    lls = []
    for z in zs:
        ref.predict()
        ref.update(z)
        lls.append(ref.log_likelihood)
    np.testing.assert_allclose(np.asarray(i1.loglik), lls, rtol=1e-8, atol=1e-8)
    with pytest.raises(ValueError, match="Q"):
        F.kalman_filter(A_LIN, H_LIN, np.eye(3), R_LIN, X0, P0)


def _central_difference(fn, x, eps=1e-6):
    return (fn(x + eps) - fn(x - eps)) / (2 * eps)


@pytest.mark.parametrize("name", ["ukf", "kf_arrays"])
def test_grad_of_loglik_wrt_process_noise_matches_finite_differences(name):
    """``jax.grad`` of the summed log-likelihood through ``run`` w.r.t. a process-noise variance."""
    zs = jnp.asarray(simulate(4, 25) if name == "ukf" else linear_data(4, 25))
    if name == "ukf":
        flt = F.build_ukf(nonlinear_model())

        def with_q(q00):
            q = flt.params.process_noise
            return flt.params._replace(process_noise=q._replace(covs=q.covs.at[0, 0, 0].set(q00)))
    else:
        flt = F.kalman_filter(A_LIN, H_LIN, Q, R_LIN, X0, P0)

        def with_q(q00):
            return flt.params._replace(Q=flt.params.Q.at[0, 0].set(q00))

    def total(q00):
        return jnp.sum(F.run(flt, zs, params=with_q(q00))[1].loglik)

    g = float(jax.jit(jax.grad(total))(Q[0, 0]))
    fd = float(_central_difference(jax.jit(total), Q[0, 0]))
    assert np.isfinite(g) and abs(g) > 1e-3
    np.testing.assert_allclose(g, fd, rtol=1e-5)


def test_vmap_over_measurement_noise_equals_loop():
    flt = F.build_ckf(nonlinear_model())
    zs = jnp.asarray(simulate(5, 20))
    scales = jnp.array([0.5, 1.0, 3.0])

    def loglik(scale):
        r = flt.params.measurement_noise
        return F.run(flt, zs, params=flt.params._replace(measurement_noise=r._replace(covs=r.covs * scale)))[
            1
        ].loglik

    batched = jax.jit(jax.vmap(loglik))(scales)
    for i, s in enumerate(scales):
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(jax.jit(loglik)(s)), rtol=1e-12)
