"""IMM: agreement with FilterPy's IMMEstimator (two Kalman filters, 100 steps, float64), identical
models reduce to the local filter, NaN measurements, jit/vmap, square-root locals, gradients with
respect to a process-noise entry of ``filter.params`` against central finite differences, jit == eager
step by step, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import filters as F
from gmjax.filters.base import StepInputs
from gmjax.filters.imm import IMMParams
from gmjax.mixture import GaussianMixture as GM
from gmjax.models import StateSpaceModel

T = 100
CV = np.array([[1.0, 1.0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 1.0], [0, 0, 0, 1.0]])
DAMPED = np.array([[1.0, 1.0, 0, 0], [0, 0.8, 0, 0], [0, 0, 1.0, 1.0], [0, 0, 0, 0.8]])
H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
Q1 = np.diag([0.01, 0.01, 0.01, 0.01])
Q2 = np.diag([0.5, 1.0, 0.5, 1.0])
R = np.diag([1.0, 1.0])
X0 = np.array([0.0, 1.0, 0.0, 0.5])
P0 = np.diag([2.0, 0.5, 2.0, 0.5])
TRANS = np.array([[0.95, 0.05], [0.1, 0.9]])
MU0 = np.array([0.6, 0.4])


def make_model(Fm, Qm, dtype=jnp.float64):
    Fj, Hj = jnp.asarray(Fm, dtype), jnp.asarray(H, dtype)
    return StateSpaceModel(
        lambda x, t: Fj @ x,
        lambda x, t: Hj @ x,
        GM.create([1.0], [np.zeros(4)], [Qm], dtype=dtype),
        GM.create([1.0], [np.zeros(2)], [R], dtype=dtype),
        GM.create([1.0], [X0], [P0], dtype=dtype),
    )


def data(seed=0, steps=T):
    rng = np.random.default_rng(seed)
    x = X0.copy()
    zs = []
    for k in range(steps):
        Fm, Qm = (CV, Q1) if (k // 25) % 2 == 0 else (DAMPED, Q2)  # regime switches
        x = Fm @ x + rng.multivariate_normal(np.zeros(4), Qm)
        zs.append(H @ x + rng.multivariate_normal(np.zeros(2), R))
    return np.array(zs)


def test_imm_matches_filterpy():
    from filterpy.kalman import IMMEstimator, KalmanFilter

    zs = data()
    kfs = []
    for Fm, Qm in ((CV, Q1), (DAMPED, Q2)):
        kf = KalmanFilter(4, 2)
        kf.x, kf.P, kf.F, kf.H, kf.Q, kf.R = X0.copy(), P0.copy(), Fm, H, Qm, R
        kfs.append(kf)
    imm = IMMEstimator(kfs, MU0.copy(), TRANS)
    xs, Ps, mus, x1 = [], [], [], []
    for z in zs:
        imm.predict()
        imm.update(z)
        xs.append(imm.x.copy()), Ps.append(imm.P.copy()), mus.append(imm.mu.copy())
        x1.append(kfs[1].x.copy())
    ours = F.build_imm([make_model(CV, Q1), make_model(DAMPED, Q2)], TRANS, filter="kf", initial_probs=MU0)
    assert isinstance(ours.params, IMMParams)
    states, infos = jax.jit(lambda z: F.run(ours, z))(jnp.asarray(zs))
    mean, cov = infos.mean, infos.cov
    np.testing.assert_allclose(np.asarray(mean), np.array(xs), rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(np.asarray(cov), np.array(Ps), rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(np.asarray(infos.extra["model_probs"]), np.array(mus), rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(np.asarray(states.states.mean[:, 1]), np.array(x1), rtol=1e-8, atol=1e-8)
    # the model probabilities follow the regime switches (a sanity check on the data)
    mu = np.asarray(infos.extra["model_probs"])
    assert mu[15:25, 0].mean() > 0.5 and mu[35:50, 1].mean() > 0.5


@pytest.mark.parametrize("kind", ["kf", pytest.param("ckf", marks=pytest.mark.slow)])
def test_identical_models_equal_the_local_filter(kind):
    zs = jnp.asarray(data(1, 40))
    m = make_model(CV, Q1)
    imm = F.build_imm([m, m, m], [[0.8, 0.1, 0.1], [0.2, 0.7, 0.1], [0.3, 0.3, 0.4]], filter=kind)
    single = {"kf": F.build_kf, "ckf": F.build_ckf}[kind](m)
    s_imm, i_imm = jax.jit(lambda z: F.run(imm, z))(zs)
    s_one, i_one = jax.jit(lambda z: F.run(single, z))(zs)
    mean, cov = i_imm.mean, i_imm.cov
    np.testing.assert_allclose(np.asarray(mean), np.asarray(s_one.mean), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(cov), np.asarray(s_one.cov), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(i_imm.loglik), np.asarray(i_one.loglik), rtol=1e-10)


def test_sqrt_local_filters_and_nan_measurement():
    zs = np.asarray(data(2, 12))
    zs[5] = np.nan
    models = [make_model(CV, Q1), make_model(DAMPED, Q2)]
    a = F.build_imm(models, TRANS, filter="sckf", initial_probs=MU0)
    b = F.build_imm(models, TRANS, filter="ckf", initial_probs=MU0)
    sa, ia = jax.jit(lambda z: F.run(a, z))(jnp.asarray(zs))
    sb, ib = jax.jit(lambda z: F.run(b, z))(jnp.asarray(zs))
    ma, Pa = ia.mean, ia.cov
    mb, Pb = ib.mean, ib.cov
    np.testing.assert_allclose(np.asarray(ma), np.asarray(mb), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(Pa), np.asarray(Pb), rtol=1e-9, atol=1e-9)
    # NaN step: log-likelihood 0 and the model probabilities are the predicted c = mu P
    assert float(ib.loglik[5]) == 0.0
    mu4 = np.asarray(ib.extra["model_probs"][4])
    np.testing.assert_allclose(np.asarray(ib.extra["model_probs"][5]), mu4 @ TRANS, rtol=1e-12)


def test_jit_eager_and_vmap_loop():
    models = [make_model(CV, Q1), make_model(DAMPED, Q2)]
    imm = F.build_imm(models, TRANS, filter="kf")
    zs = jnp.asarray(np.stack([data(s, 8) for s in range(3)]))
    go = lambda z: F.run(imm, z)  # noqa: E731
    eager = go(zs[0])
    batched = jax.jit(jax.vmap(go))(zs)
    np.testing.assert_allclose(np.asarray(eager[1].loglik), np.asarray(batched[1].loglik[0]), rtol=1e-12)
    jgo = jax.jit(go)
    np.testing.assert_allclose(np.asarray(eager[1].loglik), np.asarray(jgo(zs[0])[1].loglik), rtol=1e-12)
    for i in range(1, 3):
        one = jgo(zs[i])
        np.testing.assert_allclose(
            np.asarray(one[1].extra["model_probs"]),
            np.asarray(batched[1].extra["model_probs"][i]),
            rtol=1e-12,
        )


def test_float32():
    models = [make_model(CV, Q1, jnp.float32), make_model(DAMPED, Q2, jnp.float32)]
    imm = F.build_imm(models, TRANS, filter="kf")
    s, i = jax.jit(lambda z: F.run(imm, z))(jnp.asarray(data(3, 20), jnp.float32))
    assert i.extra["model_probs"].dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(i.loglik)))
    np.testing.assert_allclose(np.asarray(i.extra["model_probs"]).sum(1), 1.0, rtol=1e-5)


def _with_q_entry(params, value, model=1, index=(0, 1, 1)):
    """``params`` with one process-noise covariance entry of ``models[model]`` set to ``value``
    (the symmetric partner follows when off-diagonal)."""
    mp = params.models[model]
    covs = mp.process_noise.covs.at[index].set(value)
    covs = covs.at[(index[0], index[2], index[1])].set(value)
    models = list(params.models)
    models[model] = mp._replace(process_noise=mp.process_noise._replace(covs=covs))
    return params._replace(models=tuple(models))


def test_grad_of_loglik_wrt_process_noise_matches_finite_difference():
    models = [make_model(CV, Q1), make_model(DAMPED, Q2)]
    imm = F.build_imm(models, TRANS, filter="kf", initial_probs=MU0)
    zs = jnp.asarray(data(4, 15))
    q0 = float(imm.params.models[1].process_noise.covs[0, 1, 1])

    def total(q):
        return jnp.sum(F.run(imm, zs, params=_with_q_entry(imm.params, q))[1].loglik)

    g = jax.jit(jax.grad(total))(q0)
    eps = 1e-5
    total_jit = jax.jit(total)  # (compiled once: eager, the run's ops compile one by one)
    fd = (total_jit(q0 + eps) - total_jit(q0 - eps)) / (2 * eps)
    assert np.isfinite(float(g))
    np.testing.assert_allclose(float(g), float(fd), rtol=1e-6, atol=1e-8)
    # the transition matrix is a parameter too: vmap over two of them
    trans = jnp.stack([imm.params.transition, jnp.asarray([[0.5, 0.5], [0.5, 0.5]])])
    loglik = jax.jit(lambda P: F.run(imm, zs, params=imm.params._replace(transition=P))[1].loglik)
    out = jax.vmap(loglik)(trans)
    np.testing.assert_allclose(out[0], loglik(imm.params.transition), rtol=1e-12)
    assert not np.allclose(out[0], out[1])


def test_jit_equals_eager_step_by_step():
    zs = np.asarray(data(5, 6))
    zs[3] = np.nan
    models = [make_model(CV, Q1), make_model(DAMPED, Q2)]
    imm = F.build_imm(models, TRANS, filter="ekf", initial_probs=MU0)
    _, jitted = jax.jit(lambda z: F.run(imm, z))(jnp.asarray(zs))
    state = imm.init(imm.params)
    for k in range(zs.shape[0]):
        inputs = StepInputs(t=jnp.asarray(k + 1, jnp.int32))
        state = imm.predict(imm.params, state, inputs)
        state, info = imm.update(imm.params, state, jnp.asarray(zs[k]), inputs)
        np.testing.assert_allclose(info.mean, jitted.mean[k], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(info.cov, jitted.cov[k], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(info.loglik, jitted.loglik[k], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(info.extra["model_probs"], jitted.extra["model_probs"][k], rtol=1e-12)
    assert int(jitted.n_components[0]) == 2 and jitted.reduction is None
    # the NaN row (step 3) is the only flagged step: a predict-only step is recorded
    np.testing.assert_array_equal(np.asarray(jitted.flags.nonfinite_measurement), np.arange(6) == 3)
    assert not np.any(np.asarray(jitted.flags.repaired | jitted.flags.overflow | jitted.flags.degenerate))


def test_bad_input_raises():
    m = make_model(CV, Q1)
    with pytest.raises(ValueError, match="transition: rows"):
        F.build_imm([m, m], [[0.5, 0.4], [0.5, 0.5]])
    with pytest.raises(ValueError, match="transition: expected"):
        F.build_imm([m, m], np.eye(3))
    with pytest.raises(ValueError, match="non-negative"):
        F.build_imm([m, m], [[1.5, -0.5], [0.5, 0.5]])
    with pytest.raises(ValueError, match="initial_probs"):
        F.build_imm([m, m], TRANS, initial_probs=[0.5, 0.6])
    with pytest.raises(ValueError, match="filter"):
        F.build_imm([m, m], TRANS, filter="magic")
    other = m._replace(measurement_noise=GM.create([1.0], [[0.0]], [[[1.0]]]), h=lambda x, t: x[:1])
    with pytest.raises(ValueError, match="models"):
        F.build_imm([m, other], TRANS)
    with pytest.raises(ValueError, match="models"):
        F.build_imm([], np.zeros((0, 0)))
