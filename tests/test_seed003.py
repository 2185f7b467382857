"""Seed 003 §4.2 scenarios and the IMM with Gaussian-sum model filters (``build_imm_gsf``).

Independent checks: the CS/CT transitions against the constant-acceleration matrix, ``scipy.linalg.expm``
and the analytic circle; the simulator's noise and prior against the stated mixtures (standard
errors, a Kolmogorov–Smirnov test); the manoeuvre timing; ``build_imm_gsf`` against a plain NumPy
enumeration of the exact jump-Markov posterior (bank of Kalman filters over model sequences and noise
components), against ``build_gsf`` with one model and against ``build_imm`` with one-component
noises and no model switching; jit == eager, vmap == loop, float32, extra padded slots; the
gradient of the summed log-likelihood with respect to a process-noise entry of ``filter.params``
against central finite differences.
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.stats

from gmjax import filters as F
from gmjax.filters.base import StepInputs
from gmjax.filters.gsf import build_gsf
from gmjax.filters.imm import IMMGSFParams, build_imm_gsf
from gmjax.mixture import GaussianMixture as GM
from gmjax.models import StateSpaceModel, simulate
from gmjax.reduction import GMRCM, PruneTop, Runnalls
from gmjax.scenarios import manoeuvring_target

# ---------------------------------------------------------------------------------------------
# Scenario


def test_cs_transition_is_constant_acceleration():
    for alpha, dt in ((0.01, 1.0), (0.3, 0.5)):
        Fcs = manoeuvring_target.cs_transition(alpha, dt)
        ca = np.array([[1, dt, dt**2 / 2], [0, 1, dt], [0, 0, 1]])
        np.testing.assert_allclose(Fcs, ca, rtol=0, atol=1e-9)


def test_ct_transition_matches_expm_and_the_circle():
    w, dt = 0.02 * np.pi, 1.0
    A = np.array([[0, 1, 0], [0, 0, 1], [0, -(w**2), 0]])
    np.testing.assert_allclose(manoeuvring_target.ct_transition(w, dt), scipy.linalg.expm(A * dt), atol=1e-12)
    # one axis of a uniform circular motion: x = c + R cos(w t + phi)
    c, R, phi = 300.0, 2500.0, 0.3
    t = np.arange(0, 201)
    traj = np.stack(
        [c + R * np.cos(w * t + phi), -R * w * np.sin(w * t + phi), -R * w**2 * np.cos(w * t + phi)], 1
    )
    Fct = manoeuvring_target.ct_transition(w, dt)
    np.testing.assert_allclose(traj[1:], traj[:-1] @ Fct.T, rtol=1e-10, atol=1e-8)


def test_scenario_shapes_and_step_maneuver_timing():
    sc = manoeuvring_target.tracking("step")
    assert sc.n_steps == 200 and sc.position_dims == (0,)
    xs, zs, ts = simulate(sc, jax.random.key(1))
    assert xs.shape == (201, 3) and zs.shape == (200, 3) and ts.shape == (200,)
    xs = np.asarray(xs)
    t = np.arange(201)
    expected_a = np.where(t < 50, 10.0, np.where(t < 100, 20.0, -10.0))
    np.testing.assert_array_equal(xs[:, 2], expected_a)
    # constant acceleration over every sampling interval, no process noise
    np.testing.assert_allclose(xs[1:, 1], xs[:-1, 1] + xs[:-1, 2], rtol=1e-12)
    np.testing.assert_allclose(xs[1:, 0], xs[:-1, 0] + xs[:-1, 1] + xs[:-1, 2] / 2, rtol=1e-12)


def test_circular_truth_is_the_ct_motion():
    sc = manoeuvring_target.tracking("circular")
    xs, _, _ = simulate(sc, jax.random.key(2))
    xs = np.asarray(xs)
    Fct = manoeuvring_target.ct_transition()
    expected = [xs[0]]
    for _ in range(200):
        expected.append(Fct @ expected[-1])
    np.testing.assert_allclose(xs, np.array(expected), rtol=1e-9, atol=1e-6)
    # acceleration = -w^2 (x - centre): the centre is fixed along the trajectory
    w = 0.02 * np.pi
    centre = xs[:, 0] + xs[:, 2] / w**2
    np.testing.assert_allclose(centre, centre[0], rtol=1e-9)


def test_simulated_noise_and_prior_match_the_stated_mixtures():
    sc = manoeuvring_target.tracking("circular", truth_process_noise=True)
    n = 4000
    keys = jax.random.split(jax.random.key(3), n)
    v = np.asarray(jax.vmap(lambda k: sc.sample_measurement_noise(k, 1))(keys))
    x0 = np.asarray(jax.vmap(sc.sample_initial)(keys))
    w = np.asarray(jax.vmap(lambda k: sc.sample_process_noise(k, 1))(keys))
    for draws, gm in ((v, sc.model.measurement_noise), (x0, sc.model.prior), (w, sc.model.process_noise)):
        wts, mu, P = (np.asarray(a) for a in (gm.weights, gm.means, gm.covs))
        mean = wts @ mu
        dev = mu - mean
        cov = np.einsum("k,kij->ij", wts, P) + np.einsum("k,ki,kj->ij", wts, dev, dev)
        se_mean = np.sqrt(np.diag(cov) / n)
        assert np.all(np.abs(draws.mean(0) - mean) < 4.5 * se_mean)
        sq = (draws - draws.mean(0)) ** 2
        se_var = sq.std(0, ddof=1) / np.sqrt(n)
        assert np.all(np.abs(sq.mean(0) - np.diag(cov)) < 4.5 * se_var)
    # the position noise is the bimodal mixture 0.5 N(10, 100) + 0.5 N(-10, 100), not its moment match
    cdf = lambda x: 0.5 * scipy.stats.norm.cdf(x, 10, 10) + 0.5 * scipy.stats.norm.cdf(x, -10, 10)  # noqa: E731
    assert scipy.stats.kstest(v[:, 0], cdf).pvalue > 1e-3
    # process noise off by default
    sc0 = manoeuvring_target.tracking("circular")
    assert np.all(np.asarray(sc0.sample_process_noise(keys[0], 1)) == 0)


def test_scenario_bad_input():
    with pytest.raises(ValueError, match="motion"):
        manoeuvring_target.tracking("zigzag")
    with pytest.raises(ValueError, match="alpha"):
        manoeuvring_target.cs_transition(0.0)
    with pytest.raises(ValueError, match="omega"):
        manoeuvring_target.ct_transition(-1.0)


# ---------------------------------------------------------------------------------------------
# IMM with Gaussian-sum model filters: exact posterior of a jump-Markov linear system


F1 = np.array([[1.0, 1.0], [0.0, 1.0]])
F2 = np.array([[1.0, 0.5], [0.0, 0.7]])
H1 = np.array([[1.0, 0.0]])
H2 = np.array([[1.0, 0.2]])
PRIOR = ([0.7, 0.3], [[0.0, 1.0], [1.0, -0.5]], [np.diag([1.0, 0.5]), np.diag([0.6, 0.3])])
Q_GM = ([0.8, 0.2], [[0.0, 0.0], [0.3, -0.2]], [np.diag([0.1, 0.05]), np.diag([0.4, 0.2])])
R_GM = ([0.6, 0.4], [[0.2], [-0.5]], [np.array([[0.5]]), np.array([[1.5]])])
TRANS = np.array([[0.9, 0.1], [0.3, 0.7]])
MU0 = np.array([0.55, 0.45])


def _linear(Fm, Hm, dtype=jnp.float64, q=Q_GM, r=R_GM, prior=PRIOR):
    Fj, Hj = jnp.asarray(Fm, dtype), jnp.asarray(Hm, dtype)
    return StateSpaceModel(
        lambda x, t: Fj @ x,
        lambda x, t: Hj @ x,
        GM.create(*q, dtype=dtype),
        GM.create(*r, dtype=dtype),
        GM.create(*prior, dtype=dtype),
    )


def exact_jmls(zs, Fs, Hs, trans, mu0, prior, q, r):
    """NumPy: enumerate every (initial model, prior component, model / noise sequence) hypothesis."""
    hyps = [
        (mu0[m] * w, np.array(mean), np.array(P), m) for m in range(len(Fs)) for w, mean, P in zip(*prior)
    ]
    out = []
    total_prev = sum(h[0] for h in hyps)
    for z in zs:
        new = []
        for (w, mean, P, i), j in itertools.product(hyps, range(len(Fs))):
            for gq, mq, Qq in zip(*q):
                mp, Pp = Fs[j] @ mean + mq, Fs[j] @ P @ Fs[j].T + Qq
                for br, mr, Rr in zip(*r):
                    S = Hs[j] @ Pp @ Hs[j].T + Rr
                    zhat = Hs[j] @ mp + mr
                    K = Pp @ Hs[j].T @ np.linalg.inv(S)
                    lik = scipy.stats.multivariate_normal.pdf(z, zhat, S)
                    new.append((w * trans[i, j] * gq * br * lik, mp + K @ (z - zhat), Pp - K @ S @ K.T, j))
        hyps = new
        total = sum(h[0] for h in hyps)
        ws = np.array([h[0] for h in hyps]) / total
        means = np.array([h[1] for h in hyps])
        mean = ws @ means
        dev = means - mean
        cov = np.einsum("k,kij->ij", ws, np.array([h[2] for h in hyps])) + np.einsum(
            "k,ki,kj->ij", ws, dev, dev
        )
        probs = np.array([ws[[h[3] == j for h in hyps]].sum() for j in range(len(Fs))])
        out.append((mean, cov, probs, np.log(total / total_prev)))
        total_prev = total
    return out


ZS = np.array([[0.4], [1.9]])


def test_imm_gsf_equals_exact_jump_markov_posterior_and_ignores_padding():
    models = [_linear(F1, H1), _linear(F2, H2)]
    ref = exact_jmls(ZS, [F1, F2], [H1, H2], TRANS, MU0, PRIOR, Q_GM, R_GM)
    # per model after 2 steps: 2^2 model histories x 2 prior comps x (2 x 2)^2 noise pairs = 128
    results = []
    for capacity in (128, 160):
        filt = build_imm_gsf(models, TRANS, local="ekf", reducer=None, capacity=capacity, initial_probs=MU0)
        _, infos = jax.jit(lambda zs, f=filt: F.run(f, zs))(jnp.asarray(ZS))
        assert not np.any(np.asarray(infos.flags.overflow))
        for k, (mean, cov, probs, loglik) in enumerate(ref):
            np.testing.assert_allclose(infos.mean[k], mean, rtol=1e-9, atol=1e-10)
            np.testing.assert_allclose(infos.cov[k], cov, rtol=1e-9, atol=1e-10)
            np.testing.assert_allclose(infos.extra["model_probs"][k], probs, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(infos.loglik[k], loglik, rtol=1e-9)
        results.append(infos)
    assert int(results[0].n_components[-1]) == 256
    leaves = [jax.tree_util.tree_leaves((r.mean, r.cov, r.extra["model_probs"])) for r in results]
    for a, b in zip(*leaves):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize(
    "reducer",
    [
        PruneTop(num_out=4, capacity=4),
        Runnalls(num_out=4, capacity=4),
        GMRCM(alpha=0.3, capacity=4, grid_size=5, newton_steps=0),
    ],
    ids=["gmrp", "runnalls", "gmrcm-stateful"],
)
def test_one_model_imm_gsf_is_the_gsf(reducer):
    sc = manoeuvring_target.tracking("step")
    model = manoeuvring_target.imm_models()[0]
    _, zs, _ = simulate(sc._replace(n_steps=12), jax.random.key(5))
    imm = build_imm_gsf([model], [[1.0]], reducer=reducer, capacity=4)
    gsf = build_gsf(model, "ekf", reducer, capacity=4, track_ise=False)
    _, a = jax.jit(lambda zs: F.run(imm, zs, key=jax.random.key(9)))(zs)
    _, b = jax.jit(lambda zs: F.run(gsf, zs, key=jax.random.key(9)))(zs)
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(a.loglik, b.loglik, rtol=1e-12)
    np.testing.assert_array_equal(a.n_components, b.n_components)
    np.testing.assert_allclose(a.reduction.cost, b.reduction.cost, rtol=1e-12, atol=1e-14)


def test_imm_gsf_with_gaussian_noises_and_no_switching_is_the_imm():
    one = ([1.0], [[0.0, 0.0]], [np.diag([0.1, 0.05])])
    r1 = ([1.0], [[0.0]], [np.array([[0.5]])])
    p1 = ([1.0], [[0.0, 1.0]], [np.diag([1.0, 0.5])])
    models = [_linear(F1, H1, q=one, r=r1, prior=p1), _linear(F2, H2, q=one, r=r1, prior=p1)]
    rng = np.random.default_rng(0)
    zs = jnp.asarray(np.cumsum(rng.normal(size=(15, 1)), 0))
    eye = np.eye(2)
    a_filt = build_imm_gsf(models, eye, local="ekf", capacity=1, initial_probs=MU0)
    b_filt = F.build_imm(models, eye, filter="kf", initial_probs=MU0)
    _, a = jax.jit(lambda zs: F.run(a_filt, zs))(zs)
    _, b = jax.jit(lambda zs: F.run(b_filt, zs))(zs)
    mean_b, cov_b = b.mean, b.cov
    np.testing.assert_allclose(a.extra["model_probs"], b.extra["model_probs"], rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(a.loglik, b.loglik, rtol=1e-10)
    np.testing.assert_allclose(a.mean, mean_b, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(a.cov, cov_b, rtol=1e-10, atol=1e-12)


def _seed003_filter(dtype=jnp.float64, capacity=4):
    return build_imm_gsf(
        manoeuvring_target.imm_models(dtype=dtype),
        manoeuvring_target.TRANSITION,
        reducer=PruneTop(num_out=capacity, capacity=capacity),
        capacity=capacity,
    )


def test_imm_gsf_jit_eager_vmap_loop_float32_and_missing_measurement():
    sc = manoeuvring_target.tracking("circular")._replace(n_steps=4)
    keys = jax.random.split(jax.random.key(7), 3)
    zs = jnp.stack([simulate(sc, k)[1] for k in keys])
    zs = zs.at[:, 1].set(jnp.nan)  # a predict-only step
    filt = _seed003_filter()
    run = lambda z: F.run(filt, z)[1]  # noqa: E731
    batched = jax.jit(jax.vmap(run))(zs)
    single_run = jax.jit(run)
    for i in range(3):  # vmap == Python loop over runs
        single = single_run(zs[i])
        np.testing.assert_allclose(batched.mean[i], single.mean, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(
            batched.extra["model_probs"][i], single.extra["model_probs"], rtol=1e-12, atol=1e-14
        )
    # eager, step by step (no jit) == jit
    state = filt.init(filt.params)
    for k in range(2):
        inputs = StepInputs(t=jnp.asarray(k + 1, jnp.int32))
        state = filt.predict(filt.params, state, inputs)
        prior_probs = np.exp(np.asarray(state.log_probs))
        state, info = filt.update(filt.params, state, zs[0, k], inputs)
        np.testing.assert_allclose(info.mean, batched.mean[0, k], rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(
            info.extra["model_probs"], batched.extra["model_probs"][0, k], rtol=1e-10, atol=1e-13
        )
    # the NaN step is predict-only: log-likelihood 0, model probabilities = the predicted ones
    assert float(info.loglik) == 0.0
    np.testing.assert_allclose(info.extra["model_probs"], prior_probs, rtol=1e-12)
    assert np.all(np.isfinite(np.asarray(batched.mean)))
    # float32 follows float64
    f32 = _seed003_filter(jnp.float32)
    out32 = jax.jit(lambda z: F.run(f32, z)[1])(zs[0].astype(jnp.float32))
    assert out32.mean.dtype == jnp.float32
    np.testing.assert_allclose(out32.mean, batched.mean[0], rtol=2e-3, atol=0.05)
    np.testing.assert_allclose(out32.extra["model_probs"], batched.extra["model_probs"][0], atol=2e-3)


@pytest.mark.slow  # 35 s of compiling; the IMM's (tests/filters/test_imm.py) and the GSF's gradients run by default
def test_imm_gsf_grad_wrt_process_noise_matches_finite_difference():
    models = [_linear(F1, H1), _linear(F2, H2)]
    filt = build_imm_gsf(
        models, TRANS, local="ekf", reducer=Runnalls(num_out=8, capacity=8), capacity=8, initial_probs=MU0
    )
    assert isinstance(filt.params, IMMGSFParams)

    def with_q(q):  # process-noise covariance entry (component 1, [1, 1]) of model 2
        p = filt.params
        noise = p.models[1].process_noise
        m1 = p.models[1]._replace(process_noise=noise._replace(covs=noise.covs.at[1, 1, 1].set(q)))
        return p._replace(models=(p.models[0], m1))

    def total(q):
        return jnp.sum(F.run(filt, jnp.asarray(ZS), params=with_q(q))[1].loglik)

    q0 = float(filt.params.models[1].process_noise.covs[1, 1, 1])
    g = jax.jit(jax.grad(total))(q0)
    eps = 1e-5
    fd = (total(q0 + eps) - total(q0 - eps)) / (2 * eps)
    assert np.isfinite(float(g))
    np.testing.assert_allclose(float(g), float(fd), rtol=1e-6, atol=1e-9)


@pytest.mark.slow
def test_imm_gsf_jit_equals_eager_with_a_stateful_reducer_and_a_key():
    sc = manoeuvring_target.tracking("step")._replace(n_steps=3)
    _, zs, ts = simulate(sc, jax.random.key(11))
    gm_filt = build_imm_gsf(
        manoeuvring_target.imm_models(),
        manoeuvring_target.TRANSITION,
        local="ekf",
        reducer=GMRCM(alpha=0.3, capacity=4, grid_size=5, newton_steps=0),
        capacity=4,
    )
    key = jax.random.key(4)
    _, jitted = jax.jit(lambda z, k: F.run(gm_filt, z, ts, key=k))(zs, key)
    k_init, k_steps = jax.random.split(key)  # the key stream of F.run
    state = gm_filt.init(gm_filt.params, key=k_init)
    for k, k_step in enumerate(jax.random.split(k_steps, 3)):
        k_pred, k_upd = jax.random.split(k_step)
        inputs = StepInputs(t=ts[k])
        state = gm_filt.predict(gm_filt.params, state, inputs, key=k_pred)
        state, info = gm_filt.update(gm_filt.params, state, zs[k], inputs, key=k_upd)
        np.testing.assert_allclose(info.mean, jitted.mean[k], rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(info.loglik, jitted.loglik[k], rtol=1e-10)
        np.testing.assert_array_equal(state.modes.reducer_state.low_count.shape, (2, 4))
    assert jitted.extra["mode_reduction"].cost.shape == (3, 2)
    np.testing.assert_allclose(
        jitted.reduction.cost,
        (jitted.extra["model_probs"] * jitted.extra["mode_reduction"].cost).sum(1),
        rtol=1e-12,
    )


def test_imm_gsf_bad_input():
    models = manoeuvring_target.imm_models()
    with pytest.raises(ValueError, match="transition"):
        build_imm_gsf(models, np.eye(3))
    with pytest.raises(ValueError, match="transition"):
        build_imm_gsf(models, [[0.5, 0.6], [0.5, 0.5]])
    with pytest.raises(ValueError, match="initial_probs"):
        build_imm_gsf(models, manoeuvring_target.TRANSITION, initial_probs=[1.0, 1.0])
    with pytest.raises(ValueError, match="capacity"):
        build_imm_gsf(models, manoeuvring_target.TRANSITION, capacity=0)
    with pytest.raises(ValueError, match="models"):
        build_imm_gsf([], np.zeros((0, 0)))
    two_q = GM.create([0.5, 0.5], [np.zeros(3), np.ones(3)], [np.eye(3), np.eye(3)])
    with pytest.raises(ValueError, match="models: all models must have the same numbers"):
        build_imm_gsf([models[0], models[1]._replace(process_noise=two_q)], manoeuvring_target.TRANSITION)
