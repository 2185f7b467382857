"""RTS and Gaussian-sum smoothers against FilterPy, a closed form and a dense-grid smoother."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import mixture as gmm
from gmjax import quadrature
from gmjax.filters import build_gsf, build_kf, build_ukf, run
from gmjax.filters.smoother import gaussian_sum_smoother, rts_linear, rts_smoother
from gmjax.mixture import GaussianMixture
from gmjax.models import StateSpaceModel
from gmjax.reduction import Runnalls
from references import grid_np

jax.config.update("jax_enable_x64", True)

F = np.array([[1.0, 0.5], [0.0, 0.95]])
H = np.array([[1.0, 0.0]])
Q = np.array([[0.05, 0.02], [0.02, 0.1]])
R = np.array([[0.4]])
M0 = np.array([0.5, -0.2])
P0 = np.array([[1.0, 0.1], [0.1, 0.5]])


def _linear_model():
    Fj, Hj = jnp.asarray(F), jnp.asarray(H)
    return StateSpaceModel(
        f=lambda x, t: Fj @ x,
        h=lambda x, t: Hj @ x,
        process_noise=gmm.from_gaussian(jnp.zeros(2), jnp.asarray(Q)),
        measurement_noise=gmm.from_gaussian(jnp.zeros(1), jnp.asarray(R)),
        prior=gmm.from_gaussian(jnp.asarray(M0), jnp.asarray(P0)),
    )


def _data(T=12, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.multivariate_normal(M0, P0)
    zs = []
    for _ in range(T):
        x = F @ x + rng.multivariate_normal(np.zeros(2), Q)
        zs.append(H @ x + rng.normal(0, np.sqrt(R[0, 0]), 1))
    return np.asarray(zs)


def _filterpy_kf():
    from filterpy.kalman import KalmanFilter

    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P, kf.F, kf.H, kf.Q, kf.R = M0.copy(), P0.copy(), F.copy(), H.copy(), Q.copy(), R.copy()
    return kf


def test_rts_equals_filterpy():
    pytest.importorskip("filterpy")
    zs = _data()
    kf = _filterpy_kf()
    xs, Ps, _, _ = kf.batch_filter(list(zs))
    xs_s, Ps_s, Ks, _ = kf.rts_smoother(xs, Ps)
    # the smoother alone, on FilterPy's filtered moments
    lin = rts_linear(F, Q, xs, Ps)
    np.testing.assert_allclose(lin.mean, xs_s, atol=1e-8)
    np.testing.assert_allclose(lin.cov, Ps_s, atol=1e-8)
    np.testing.assert_allclose(lin.gain[:-1], Ks[:-1], atol=1e-8)
    # the whole pipeline: gmjax KF -> model-level RTS
    model = _linear_model()
    _, infos = run(build_kf(model), jnp.asarray(zs))
    np.testing.assert_allclose(infos.mean, xs, atol=1e-8)
    sm = rts_smoother(model, infos.mean, infos.cov, method="kf")
    np.testing.assert_allclose(sm.mean, xs_s, atol=1e-8)
    np.testing.assert_allclose(sm.cov, Ps_s, atol=1e-8)


def test_rts_equals_batch_conditioning():
    """Closed form: condition the joint Gaussian of (x_1..x_T, z_1..z_T) on all the z."""
    T = 6
    zs = _data(T, seed=3)
    d = 2
    # x_k = F^k x_0 + sum_j F^{k-j} v_j; build the joint covariance of x_{1:T}
    A = np.zeros((T * d, d + T * d))  # x_{1:T} = A @ [x_0, v_1..v_T]
    for k in range(1, T + 1):
        A[(k - 1) * d : k * d, :d] = np.linalg.matrix_power(F, k)
        for j in range(1, k + 1):
            A[(k - 1) * d : k * d, d + (j - 1) * d : d + j * d] = np.linalg.matrix_power(F, k - j)
    S0 = np.zeros((d + T * d, d + T * d))
    S0[:d, :d] = P0
    for j in range(T):
        S0[d + j * d : d + (j + 1) * d, d + j * d : d + (j + 1) * d] = Q
    mx = A[:, :d] @ M0
    Sx = A @ S0 @ A.T
    Hb = np.kron(np.eye(T), H)
    Sz = Hb @ Sx @ Hb.T + np.kron(np.eye(T), R)
    K = Sx @ Hb.T @ np.linalg.inv(Sz)
    mean = mx + K @ (zs.ravel() - Hb @ mx)
    cov = Sx - K @ Hb @ Sx
    model = _linear_model()
    _, infos = run(build_kf(model), jnp.asarray(zs))
    sm = rts_smoother(model, infos.mean, infos.cov, method="ekf")
    np.testing.assert_allclose(sm.mean.reshape(-1), mean, atol=1e-10)
    for k in range(T):
        np.testing.assert_allclose(sm.cov[k], cov[k * d : (k + 1) * d, k * d : (k + 1) * d], atol=1e-10)


def test_sigma_point_rts_linear_equals_rts_and_jit():
    zs = jnp.asarray(_data())
    model = _linear_model()
    _, infos = run(build_kf(model), zs)
    ref = rts_smoother(model, infos.mean, infos.cov, method="kf")
    for method in ("ukf", "ckf", "ghkf"):
        sm = rts_smoother(model, infos.mean, infos.cov, method=method)
        np.testing.assert_allclose(sm.mean, ref.mean, atol=1e-10)
        np.testing.assert_allclose(sm.cov, ref.cov, atol=1e-10)
    jitted = jax.jit(lambda m, P: rts_smoother(model, m, P, method="ckf"))(infos.mean, infos.cov)
    np.testing.assert_allclose(jitted.mean, ref.mean, atol=1e-10)


def test_urts_equals_filterpy_ukf_smoother():
    """Särkkä's URTS on a nonlinear model, against FilterPy's UnscentedKalmanFilter.rts_smoother."""
    pytest.importorskip("filterpy")
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    alpha, beta, kappa = 0.8, 2.0, 1.0

    def fx_np(x, dt):
        return np.array([x[0] + dt * np.sin(x[1]), 0.9 * x[1] + 0.1 * np.cos(x[0])])

    def hx_np(x):
        return np.array([np.sqrt(1 + x[0] ** 2)])

    pts = MerweScaledSigmaPoints(2, alpha, beta, kappa)
    ukf = UnscentedKalmanFilter(2, 1, 1.0, hx_np, fx_np, pts)
    ukf.x, ukf.P, ukf.Q, ukf.R = M0.copy(), P0.copy(), Q.copy(), R.copy()
    zs = _data(10, seed=5)
    xs, Ps = ukf.batch_filter(list(zs))[:2]
    xs_s, Ps_s, _ = ukf.rts_smoother(xs, Ps)
    model = StateSpaceModel(
        f=lambda x, t: jnp.stack([x[0] + jnp.sin(x[1]), 0.9 * x[1] + 0.1 * jnp.cos(x[0])]),
        h=lambda x, t: jnp.sqrt(1 + x[:1] ** 2),
        process_noise=gmm.from_gaussian(jnp.zeros(2), jnp.asarray(Q)),
        measurement_noise=gmm.from_gaussian(jnp.zeros(1), jnp.asarray(R)),
        prior=gmm.from_gaussian(jnp.asarray(M0), jnp.asarray(P0)),
    )
    rule = quadrature.unscented(2, alpha, beta, kappa)
    sm = rts_smoother(model, jnp.asarray(xs), jnp.asarray(Ps), method=rule)
    np.testing.assert_allclose(sm.mean, xs_s, atol=1e-8)
    np.testing.assert_allclose(sm.cov, Ps_s, atol=1e-8)
    # and the gmjax UKF itself runs into the smoother
    _, infos = run(build_ukf(model, alpha, beta, kappa), jnp.asarray(zs))
    assert np.all(np.isfinite(rts_smoother(model, infos.mean, infos.cov, method="ukf").mean))


# --- Gaussian-sum smoother against a dense grid, scalar bimodal case ---------------------------

A1, Q1 = 0.9, 1.0
RW = np.array([0.5, 0.5])
RM = np.array([-3.0, 3.0])
RV = np.array([0.5, 0.5])


def _bimodal_model():
    return StateSpaceModel(
        f=lambda x, t: A1 * x,
        h=lambda x, t: x,
        process_noise=gmm.from_gaussian(jnp.zeros(1), jnp.full((1, 1), Q1)),
        measurement_noise=GaussianMixture.create(RW, RM[:, None], RV[:, None, None]),
        prior=gmm.from_gaussian(jnp.zeros(1), jnp.full((1, 1), 4.0)),
    )


def _bimodal_data(T, rng):
    x = rng.normal(0, 2.0)
    xs, zs = [], []
    for _ in range(T):
        x = A1 * x + rng.normal(0, np.sqrt(Q1))
        j = rng.choice(2, p=RW)
        xs.append(x)
        zs.append(x + RM[j] + rng.normal(0, np.sqrt(RV[j])))
    return np.asarray(xs), np.asarray(zs)


@functools.cache
def _gs_pair_batch(K=16):
    """One compiled kernel: GSF forward pass + GS smoother, vmapped over runs ``zs (N, T)``."""
    model = _bimodal_model()
    filt = build_gsf(model, "kf", Runnalls(num_out=K), K, track_ise=False)

    def pair(zs):
        states, infos = run(filt, zs[:, None])
        sm = gaussian_sum_smoother(model, states.mixture, reducer=Runnalls(num_out=K), method="kf")
        return infos.mean[:, 0], sm.mean[:, 0], sm.cov[:, 0, 0]

    return jax.jit(jax.vmap(pair))


@functools.cache
def _bimodal_runs(T=20, n_runs=8):
    """``(xs, zs, filtered means, smoothed means, smoothed variances)``, each ``(n_runs, T)``."""
    rng = np.random.default_rng(7)
    xs, zs = zip(*(_bimodal_data(T, rng) for _ in range(n_runs)))
    out = _gs_pair_batch()(jnp.asarray(np.stack(zs)))
    return (np.stack(xs), np.stack(zs)) + tuple(np.asarray(a) for a in out)


def test_gaussian_sum_smoother_matches_grid():
    _, zs, filt_mean, sm_mean, sm_var = (a[0] for a in _bimodal_runs())
    grid = np.linspace(-40, 40, 4001)
    npdf = lambda x, v: np.exp(-0.5 * x**2 / v) / np.sqrt(2 * np.pi * v)  # noqa: E731
    filt_g, sm_g = grid_np.grid_filter_smoother(
        grid,
        lambda x: npdf(x, 4.0),
        lambda x: A1 * x,
        lambda x: x,
        lambda v: npdf(v, Q1),
        lambda w: grid_np.gm_pdf(w, RW, RM, RV),
        zs,
    )
    grid_filt_mean = filt_g @ grid
    grid_sm_mean = sm_g @ grid
    grid_sm_var = sm_g @ grid**2 - grid_sm_mean**2
    # the forward GSF (16 components, Runnalls) is itself close to the grid filter
    np.testing.assert_allclose(filt_mean, grid_filt_mean, atol=0.02)
    # smoothed means within 2 % of the grid smoother's posterior standard deviation
    err = np.abs(np.asarray(sm_mean) - grid_sm_mean) / np.sqrt(grid_sm_var)
    verr = np.abs(np.asarray(sm_var) / grid_sm_var - 1)
    print("max |GS smoother - grid| / grid std:", err.max(), "variance rel. err:", verr.max())
    assert err.max() < 0.02, err
    assert verr.max() < 0.05, verr


def test_gaussian_sum_smoother_beats_filter_rmse():
    xs, _, fm, sm, _ = _bimodal_runs()
    rmse_f = np.sqrt(np.mean((np.asarray(fm) - xs) ** 2))
    rmse_s = np.sqrt(np.mean((np.asarray(sm) - xs) ** 2))
    print("RMSE filter", rmse_f, "smoother", rmse_s)
    assert rmse_s < 0.9 * rmse_f, (rmse_s, rmse_f)


def test_gaussian_sum_smoother_says_what_its_capacity_cannot_hold():
    """Nothing lost silently: a last filtered mixture larger than ``capacity`` is refused, and a
    backward step whose reducer keeps more live components than ``capacity`` sets ``overflow``."""
    from gmjax.reduction import PruneTop

    model = _bimodal_model()
    _, zs = _bimodal_data(6, np.random.default_rng(3))
    filt = build_gsf(model, "kf", PruneTop(num_out=4), 4, track_ise=False)
    mixtures = run(filt, jnp.asarray(zs)[:, None])[0].mixture
    assert int(gmm.n_active(jax.tree_util.tree_map(lambda a: a[-1], mixtures))) == 4
    with pytest.raises(ValueError, match="capacity: the last filtered mixture has 4 live components"):
        gaussian_sum_smoother(model, mixtures, capacity=2, method="kf")
    # the last mixture cut to its heaviest component: it fits, but a reducer keeping 4 does not
    last_mask = jnp.arange(4) == jnp.argmax(mixtures.weights[-1])
    one_last = mixtures._replace(mask=mixtures.mask.at[-1].set(last_mask))
    keeps_4 = gaussian_sum_smoother(model, one_last, capacity=2, reducer=PruneTop(num_out=4), method="kf")
    assert np.all(np.asarray(keeps_4.reduction.overflow))
    assert keeps_4.mixture.mask.shape == (6, 2)
    keeps_2 = gaussian_sum_smoother(model, one_last, capacity=2, reducer=Runnalls(num_out=2), method="kf")
    assert not np.any(np.asarray(keeps_2.reduction.overflow))
