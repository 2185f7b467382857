"""Particle filters: resamplers (unbiasedness from the standard error, structural properties),
ESS, convergence of the PF mean to the KF mean within Monte Carlo error, the regularisation
kernel's statistics, GM vs callable noises, NaN measurements, degeneracy, jit/vmap/dtypes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import filters as F
from gmjax import mixture as gmm
from gmjax.filters import pf as pfm
from gmjax.filters.base import StepInputs
from gmjax.mixture import GaussianMixture as GM
from gmjax.models import StateSpaceModel

A = np.array([[1.0, 1.0], [0.0, 1.0]])
H = np.array([[1.0, 0.0]])
Q = 0.1 * np.eye(2)
R = np.array([[0.5]])
X0 = np.array([0.0, 1.0])
P0 = np.eye(2)


def model(dtype=jnp.float64, capacity=None):
    Aj, Hj = jnp.asarray(A, dtype), jnp.asarray(H, dtype)
    return StateSpaceModel(
        lambda x, t: Aj @ x,
        lambda x, t: Hj @ x,
        GM.create([1.0], [np.zeros(2)], [Q], capacity=capacity, dtype=dtype),
        GM.create([1.0], [[0.0]], [R], capacity=capacity, dtype=dtype),
        GM.create([1.0], [X0], [P0], capacity=capacity, dtype=dtype),
    )


def data(seed=0, steps=10):
    rng = np.random.default_rng(seed)
    x = X0 + rng.multivariate_normal(np.zeros(2), P0)
    zs = []
    for _ in range(steps):
        x = A @ x + rng.multivariate_normal(np.zeros(2), Q)
        zs.append(H @ x + rng.normal(0, np.sqrt(R[0, 0]), 1))
    return jnp.asarray(np.array(zs))


W_TEST = np.array([0.05, 0.3, 0.001, 0.25, 0.199, 0.2])
_VMAPPED = {}


def batched_resampler(name):
    """``jit(vmap(resampler))`` over keys for the fixed test weights, compiled once."""
    if name not in _VMAPPED:
        lw = jnp.log(jnp.asarray(W_TEST))
        res = pfm.RESAMPLERS[name]
        _VMAPPED[name] = jax.jit(jax.vmap(lambda k: res(k, lw)))
    return _VMAPPED[name]


@pytest.mark.parametrize("name", sorted(pfm.RESAMPLERS))
def test_resampler_is_unbiased(name):
    """E[count_i] = N w_i; the tolerance is 5 standard errors of the mean count over M draws."""
    M = 4000
    idx = batched_resampler(name)(jax.random.split(jax.random.key(0), M))
    counts = np.stack([np.bincount(np.asarray(i), minlength=6) for i in idx])
    mean = counts.mean(0)
    se = counts.std(0, ddof=1) / np.sqrt(M)
    n = len(W_TEST)
    assert np.all(np.abs(mean - n * W_TEST) <= 5 * se + 1e-12), (mean, n * W_TEST, se)
    assert np.all(counts.sum(1) == n)


def test_resampler_structure():
    n = len(W_TEST)
    keys = jax.random.split(jax.random.key(1), 200)
    nw = n * W_TEST
    draws = {
        name: np.asarray(batched_resampler(name)(keys)) for name in ("systematic", "residual", "stratified")
    }
    for i in range(len(keys)):
        c_sys = np.bincount(draws["systematic"][i], minlength=n)
        assert np.all((c_sys == np.floor(nw)) | (c_sys == np.ceil(nw)))
        c_res = np.bincount(draws["residual"][i], minlength=n)
        assert np.all(c_res >= np.floor(nw))
        c_str = np.bincount(draws["stratified"][i], minlength=n)
        assert np.all(np.abs(c_str - nw) < 2)
    # integral N w_i: residual is deterministic, all counts exact
    w_int = jnp.log(jnp.array([0.5, 0.25, 0.25, 0.0]))
    c = np.bincount(np.asarray(pfm.residual(keys[0], w_int)), minlength=4)
    np.testing.assert_array_equal(c, [2, 1, 1, 0])


def test_ess_matches_numpy():
    w = np.random.default_rng(0).random(50)
    w /= w.sum()
    np.testing.assert_allclose(
        float(pfm.effective_sample_size(jnp.log(jnp.asarray(w)) + 3.0)), 1.0 / np.sum(w**2), rtol=1e-12
    )


def _kf_reference(zs):
    kf = F.build_kf(model())
    return jax.jit(lambda z: F.run(kf, z))(zs)


@pytest.mark.parametrize(
    "name",
    [
        "systematic",
        pytest.param("multinomial", marks=pytest.mark.slow),
        pytest.param("stratified", marks=pytest.mark.slow),
        pytest.param("residual", marks=pytest.mark.slow),
    ],
)
def test_pf_mean_converges_to_kf(name):
    """Replicated PFs: their average posterior mean is within 5 standard errors of the KF mean
    at every step (standard error from the spread of the replicas; the O(1/N) bias is far below
    it at N = 2000)."""
    zs = data(0, 10)
    ref, rinfo = _kf_reference(zs)
    flt = F.build_pf(model(), 2000, resampling=name, ess_threshold=0.5)
    R_ = 48

    @jax.jit
    def one(key):
        _, infos = F.run(flt, zs, key=key)
        return infos.mean, infos.loglik

    means, lls = jax.vmap(one)(jax.random.split(jax.random.key(2), R_))
    means = np.asarray(means)
    err = means.mean(0) - np.asarray(ref.mean)
    se = means.std(0, ddof=1) / np.sqrt(R_)
    assert np.all(np.abs(err) <= 5 * se), np.max(np.abs(err) / se)
    # the PFs really are close (not merely noisy): per-replica error ~ posterior sd / sqrt(N)
    post_sd = np.sqrt(np.diagonal(np.asarray(ref.cov), axis1=1, axis2=2))
    assert np.all(means.std(0) < 0.2 * post_sd)
    # total log-likelihood: log of an unbiased estimate; mean within 5 SE (Jensen bias ~ var/2)
    tot = np.asarray(lls).sum(1)
    se_ll = tot.std(ddof=1) / np.sqrt(R_)
    assert abs(tot.mean() - float(rinfo.loglik.sum())) <= 5 * se_ll + 0.5 * tot.var()


def test_regularisation_kernel_statistics():
    """With a flat likelihood, one resample + kernel step keeps the mean and inflates the
    covariance by (1 + h_opt^2) (Musso et al.), checked within the sampling error."""
    N, d = 20000, 2
    flat = StateSpaceModel(
        lambda x, t: x,
        lambda x, t: x[:1],
        GM.create([1.0], [np.zeros(2)], [np.eye(2)]),
        GM.create([1.0], [[0.0]], [[[1.0]]]),
        GM.create([1.0], [np.zeros(2)], [np.diag([1.0, 4.0])]),
    )
    flt = F.build_pf(flat, N, regularized=True, measurement_noise=lambda w: jnp.zeros(()))
    k_init, k_upd = jax.random.split(jax.random.key(3))
    st = flt.init(flt.params, key=k_init)
    new, info = jax.jit(flt.update)(flt.params, st, jnp.array([0.0]), StepInputs(t=1), key=k_upd)
    assert bool(info.extra["resampled"])
    x = np.asarray(new.particles)
    x0 = np.asarray(st.particles)
    h = (4.0 / (d + 2)) ** (1 / (d + 4)) * N ** (-1 / (d + 4))
    ratio = np.var(x, axis=0) / np.var(x0, axis=0)
    # var of a sample variance ~ 2 sigma^4 / N; the resampling adds a similar amount
    assert np.all(np.abs(ratio - (1 + h**2)) < 5 * np.sqrt(4.0 / N))
    assert np.all(np.abs(x.mean(0) - x0.mean(0)) < 5 * np.sqrt(np.var(x0, axis=0) * 2 / N))


def test_gm_and_callable_noises_agree():
    """A callable sampler / log-density doing the same thing as the GM gives identical output;
    padded slots in the noise mixtures change nothing deterministic."""
    zs = data(1, 5)
    m = model()
    q_gm, r_gm = m.process_noise, m.measurement_noise
    a = F.build_pf(m, 300)
    b = F.build_pf(
        m,
        300,
        process_noise=lambda key, shape: pfm._gm_sampler(q_gm)(key, shape),
        measurement_noise=lambda w: gmm.logpdf(r_gm, w),
    )
    key = jax.random.key(4)
    sa, ia = jax.jit(lambda k: F.run(a, zs, key=k))(key)
    sb, ib = jax.jit(lambda k: F.run(b, zs, key=k))(key)
    np.testing.assert_allclose(np.asarray(sa.particles), np.asarray(sb.particles), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(ia.loglik), np.asarray(ib.loglik), rtol=1e-12)
    # padded measurement-noise slots leave the likelihood unchanged
    w = jnp.linspace(-3.0, 3.0, 7)[:, None]
    lp = jax.jit(jax.vmap(pfm._gm_logpdf(r_gm)))(w)
    lp_pad = jax.jit(jax.vmap(pfm._gm_logpdf(gmm.pad(r_gm, 3))))(w)
    np.testing.assert_allclose(np.asarray(lp_pad), np.asarray(lp), rtol=1e-13)
    np.testing.assert_allclose(
        np.asarray(lp), -0.5 * (np.log(2 * np.pi * R[0, 0]) + np.asarray(w)[:, 0] ** 2 / R[0, 0]), rtol=1e-12
    )


def test_true_noise_sampler_is_used():
    """A Gamma process-noise simulator: the predicted particle mean moves by its mean."""
    m = model()
    shape_k, scale = 2.0, 0.5

    def gamma_noise(key, shape):
        return scale * jax.random.gamma(key, shape_k, shape + (2,))

    flt = F.build_pf(m, 50000, process_noise=gamma_noise)
    k_init, k_pred = jax.random.split(jax.random.key(5))
    st = flt.init(flt.params, key=k_init)
    moved = jax.jit(flt.predict)(flt.params, st, StepInputs(t=1), key=k_pred)
    diff = np.asarray(moved.particles) - np.asarray(st.particles) @ A.T
    se = np.sqrt(shape_k) * scale / np.sqrt(50000)
    assert np.all(np.abs(diff.mean(0) - shape_k * scale) < 5 * se)


def test_timed_per_draw_sampler():
    """A Scenario-style simulator (key, t) -> (d,) wrapped in TimedSampler: one independent
    draw per particle, and the time argument reaches it."""
    m = model()

    def simulator(key, t):
        return t + jax.random.normal(key, (2,))

    flt = F.build_pf(m, 20000, process_noise=pfm.TimedSampler(simulator))
    k_init, k_pred = jax.random.split(jax.random.key(8))
    st = flt.init(flt.params, key=k_init)
    moved = jax.jit(flt.predict)(flt.params, st, StepInputs(t=3), key=k_pred)
    v = np.asarray(moved.particles) - np.asarray(st.particles) @ A.T
    se = 1.0 / np.sqrt(20000)
    assert np.all(np.abs(v.mean(0) - 3.0) < 5 * se)
    assert np.all(np.abs(v.std(0) - 1.0) < 5 * se)
    assert abs(np.corrcoef(v[:, 0], v[:, 1])[0, 1]) < 5 * se


def test_nan_measurement_and_degeneracy_float32():
    flt = F.build_pf(model(jnp.float32), 500)
    k_init, k_pred, k_upd = jax.random.split(jax.random.key(6), 3)
    one = StepInputs(t=1)
    st = flt.init(flt.params, key=k_init)
    assert st.particles.dtype == jnp.float32
    st = jax.jit(flt.predict)(flt.params, st, one, key=k_pred)
    update = jax.jit(flt.update)
    ok, ok_info = update(flt.params, st, jnp.array([0.5], jnp.float32), one, key=k_upd)
    assert ok.particles.dtype == jnp.float32 and np.isfinite(float(ok_info.loglik))
    assert ok_info.mean.dtype == jnp.float32 and ok_info.cov.dtype == jnp.float32
    new, info = update(flt.params, st, jnp.array([jnp.nan], jnp.float32), one, key=k_upd)
    np.testing.assert_array_equal(np.asarray(new.particles), np.asarray(st.particles))
    np.testing.assert_array_equal(np.asarray(new.log_weights), np.asarray(st.log_weights))
    assert float(info.loglik) == 0.0 and not bool(info.extra["resampled"])
    # every particle impossible: flagged, weights kept, no NaN
    dead = F.build_pf(model(jnp.float32), 500, measurement_noise=lambda w: jnp.full((), -jnp.inf))
    new, info = jax.jit(dead.update)(dead.params, st, jnp.array([0.0], jnp.float32), one, key=k_upd)
    assert bool(info.flags.degenerate)
    assert np.all(np.isfinite(np.asarray(new.log_weights)))
    assert np.all(np.isfinite(np.asarray(new.particles)))


def test_jit_eager_vmap_loop():
    zs = data(2, 4)
    flt = F.build_pf(model(), 200, resampling="residual")
    keys = jax.random.split(jax.random.key(7), 3)
    go = lambda k: F.run(flt, zs, key=k)  # noqa: E731
    eager = go(keys[0])
    jitted = jax.jit(go)(keys[0])  # compiled once, reused in the loop below
    batched = jax.jit(jax.vmap(go))(keys)
    np.testing.assert_allclose(
        np.asarray(eager[0].particles), np.asarray(jitted[0].particles), rtol=1e-10, atol=1e-10
    )
    np.testing.assert_allclose(np.asarray(eager[1].loglik), np.asarray(jitted[1].loglik), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(eager[1].mean), np.asarray(jitted[1].mean), rtol=1e-10, atol=1e-10)
    jgo = jax.jit(go)
    for i in range(3):
        one = jgo(keys[i])
        np.testing.assert_allclose(
            np.asarray(one[0].particles), np.asarray(batched[0].particles[i]), rtol=1e-10, atol=1e-10
        )
        np.testing.assert_allclose(np.asarray(one[1].loglik), np.asarray(batched[1].loglik[i]), rtol=1e-10)


def test_bad_input_raises():
    m = model()
    with pytest.raises(ValueError, match="resampling"):
        F.build_pf(m, 10, resampling="bogus")
    with pytest.raises(ValueError, match="n_particles"):
        F.build_pf(m, 0)
    with pytest.raises(ValueError, match="ess_threshold"):
        F.build_pf(m, 10, ess_threshold=1.5)
    with pytest.raises(ValueError, match="process_noise"):
        F.build_pf(m, 10, process_noise=3.0)
    with pytest.raises(ValueError, match="measurement_noise"):
        F.build_pf(m, 10, measurement_noise="gaussian")
    with pytest.raises(ValueError, match="bandwidth"):
        F.build_pf(m, 10, bandwidth_scale=0.0)
    with pytest.raises(ValueError, match="process_noise"):
        F.build_pf(m, 10, process_noise=GM.create([1.0], [[0.0]], [[[1.0]]]))
    with pytest.raises(ValueError, match="measurement_noise"):
        F.build_pf(m, 10, measurement_noise=m.process_noise)
    flt = F.build_pf(m, 10)
    with pytest.raises(ValueError, match="key: the particle filter needs a PRNG key"):
        flt.init(flt.params)
    with pytest.raises(ValueError, match="key: the particle filter needs a PRNG key"):
        F.run(flt, data(0, 2))
    st = flt.init(flt.params, key=jax.random.key(0))
    with pytest.raises(ValueError, match="key"):
        flt.predict(flt.params, st, StepInputs(t=1))
    with pytest.raises(ValueError, match="key"):
        flt.update(flt.params, st, jnp.array([0.0]), StepInputs(t=1))
    with pytest.raises(ValueError, match="prior"):
        flt.init(flt.params, (jnp.zeros(2), jnp.eye(2)), key=jax.random.key(0))


def test_step_info_contract():
    """StepInfo: mean/cov are the weighted moments of the posterior particles, n_components = 1
    (int32, no mixture), the ESS / resampled diagnostics sit in ``extra``; a GM noise override lives in params."""
    zs = data(3, 4)
    q2 = GM.create([1.0], [np.zeros(2)], [2.0 * Q])
    flt = F.build_pf(model(), 100, ess_threshold=0.5, process_noise=q2)
    assert flt.params.model.process_noise is q2
    states, infos = jax.jit(lambda k: F.run(flt, zs, key=k))(jax.random.key(9))
    mean, cov = jax.vmap(pfm.pf_moments)(states)
    np.testing.assert_allclose(np.asarray(infos.mean), np.asarray(mean), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(infos.cov), np.asarray(cov), rtol=1e-12, atol=1e-12)
    assert infos.n_components.dtype == jnp.int32 and np.all(np.asarray(infos.n_components) == 1)
    assert set(infos.extra) == {"ess", "resampled"}
    ess = np.asarray(infos.extra["ess"])
    assert np.all((ess >= 1.0 - 1e-9) & (ess <= 100 + 1e-9))
    np.testing.assert_array_equal(np.asarray(infos.extra["resampled"]), ess < 50)
    assert infos.reduction is None
    assert not np.any(np.asarray(infos.flags.any()))


def test_params_are_read_at_each_call():
    """Changing ``params`` (not the closure) changes the run: ess_threshold = 0 never resamples."""
    zs = data(4, 5)
    flt = F.build_pf(model(), 200)
    go = jax.jit(lambda p, k: F.run(flt, zs, key=k, params=p))
    key = jax.random.key(10)
    _, every = go(flt.params, key)
    _, never = go(flt.params._replace(ess_threshold=jnp.asarray(0.0)), key)
    assert np.all(np.asarray(every.extra["resampled"]))
    assert not np.any(np.asarray(never.extra["resampled"]))
    assert go._cache_size() == 1  # a new threshold value does not recompile


def _stack(*trees):
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *trees)


def test_vmap_over_params_sets():
    """With a fixed key a PF's loglik is piecewise in params (resampling indices jump), so no
    gradient check over a run; ``jax.vmap`` over two params sets (process-noise covariance and
    ESS threshold) equals a Python loop over them."""
    zs = data(5, 6)
    flt = F.build_pf(model(), 150)
    p1 = flt.params
    q2 = GM.create([1.0], [np.zeros(2)], [3.0 * Q])
    p2 = p1._replace(model=p1.model._replace(process_noise=q2), ess_threshold=jnp.asarray(0.5))
    key = jax.random.key(11)
    go = jax.jit(lambda p: F.run(flt, zs, key=key, params=p))
    batched_states, batched_infos = jax.jit(jax.vmap(lambda p: F.run(flt, zs, key=key, params=p)))(
        _stack(p1, p2)
    )
    for i, p in enumerate((p1, p2)):
        states, infos = go(p)
        np.testing.assert_allclose(
            np.asarray(batched_states.particles[i]), np.asarray(states.particles), rtol=1e-10, atol=1e-10
        )
        np.testing.assert_allclose(np.asarray(batched_infos.loglik[i]), np.asarray(infos.loglik), rtol=1e-10)
        np.testing.assert_allclose(
            np.asarray(batched_infos.mean[i]), np.asarray(infos.mean), rtol=1e-10, atol=1e-10
        )
    assert not np.allclose(np.asarray(batched_infos.loglik[0]), np.asarray(batched_infos.loglik[1]))


def test_one_step_loglik_gradient_wrt_process_noise():
    """One predict + update with a fixed key is smooth in Q (the draws are x + chol(Q) eps and
    the loglik is taken before resampling): ``jax.grad`` through params matches a central finite
    difference (float64)."""
    zs = data(6, 1)
    flt = F.build_pf(model(), 300)
    key = jax.random.key(12)

    def loglik(q01):
        covs = flt.params.model.process_noise.covs.at[0, 0, 1].set(q01).at[0, 1, 0].set(q01)
        p = flt.params._replace(
            model=flt.params.model._replace(process_noise=flt.params.model.process_noise._replace(covs=covs))
        )
        return F.run(flt, zs, key=key, params=p)[1].loglik.sum()

    q01, eps = 0.02, 1e-5
    g = float(jax.jit(jax.grad(loglik))(q01))
    values = jax.jit(jax.vmap(loglik))(jnp.array([q01 + eps, q01 - eps]))
    fd = float(values[0] - values[1]) / (2 * eps)
    assert np.isfinite(g)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-8)
