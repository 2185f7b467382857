"""Gaussian sum filter engine against the local filter, an enumerated exact posterior and a NumPy GSF."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from gmjax import GaussianMixture  # noqa: E402
from gmjax import mixture as gmm  # noqa: E402
from gmjax.filters import StepInputs, build_ekf, run  # noqa: E402
from gmjax.filters.gsf import build_gsf  # noqa: E402
from gmjax.models import StateSpaceModel, simulate  # noqa: E402
from gmjax.reduction import PruneTop  # noqa: E402
from gmjax.scenarios.jump_system import jump_system  # noqa: E402
from references import gsf_np  # noqa: E402


def as_np(gm: GaussianMixture):
    live = np.asarray(gm.mask)
    return np.asarray(gm.weights)[live], np.asarray(gm.means)[live], np.asarray(gm.covs)[live]


def linear_model(dtype=jnp.float64):
    F = jnp.array([[1.0, 0.5], [0.0, 0.9]], dtype)
    H = jnp.array([[1.0, 0.0]], dtype)
    q = GaussianMixture.create(
        [0.7, 0.3], [[0.0, 0.0], [0.3, -0.2]], [np.diag([0.05, 0.1]), np.diag([0.2, 0.3])], dtype=dtype
    )
    r = GaussianMixture.create([0.8, 0.2], [[0.0], [1.5]], [[[0.3]], [[2.0]]], dtype=dtype)
    prior = GaussianMixture.create(
        [0.5, 0.5], [[-1.0, 0.0], [1.0, 0.5]], [np.eye(2), 0.5 * np.eye(2)], dtype=dtype
    )
    model = StateSpaceModel(lambda x, t: F @ x, lambda x, t: H @ x, q, r, prior)
    return model, np.asarray(F, float), np.asarray(H, float)


def test_linear_gsf_without_reduction_equals_enumerated_exact_posterior():
    model, F, H = linear_model()
    zs = np.array([[0.4], [-0.3], [1.2]])
    T = len(zs)
    capacity = 2 * 4**T  # K0 (L J)^T = 128: nothing is ever dropped
    filt = build_gsf(model, "ekf", None, capacity=capacity, track_ise=False)
    states, infos = jax.jit(lambda z: run(filt, z))(jnp.asarray(zs))
    assert not np.any(infos.flags.overflow)
    exact = gsf_np.enumerate_linear_posterior(
        as_np(model.prior), zs, F, H, as_np(model.process_noise), as_np(model.measurement_noise)
    )
    final = jax.tree_util.tree_map(lambda a: a[-1], states.mixture)
    assert int(gmm.n_active(final)) == len(exact[0])
    # compare as densities (slot order differs) and through moments
    grid = np.stack(np.meshgrid(np.linspace(-4, 5, 25), np.linspace(-4, 4, 25)), -1).reshape(-1, 2)
    ex_gm = GaussianMixture.create(*exact)
    np.testing.assert_allclose(gmm.pdf(final, grid), gmm.pdf(ex_gm, grid), rtol=1e-9, atol=1e-14)
    mu, C = gsf_np.moments(exact)
    np.testing.assert_allclose(infos.mean[-1], mu, rtol=1e-10)
    np.testing.assert_allclose(infos.cov[-1], C, rtol=1e-10)
    # the per-step log-likelihoods add up to log p(z_1:T)
    assert np.all(np.isfinite(infos.loglik))


def test_one_component_noises_capacity_one_equals_local_filter():
    sc = jump_system()
    one = lambda gm: GaussianMixture.create([1.0], gmm.mean(gm)[None], gmm.cov(gm)[None])  # noqa: E731
    model = sc.model._replace(process_noise=one(sc.model.process_noise), prior=one(sc.model.prior))
    _, zs, ts = simulate(sc._replace(n_steps=30), jax.random.key(3))
    gsf = build_gsf(model, "ekf", None, capacity=1)
    g_states, g_infos = run(gsf, zs, ts)
    e_states, _ = run(build_ekf(model), zs, ts)
    np.testing.assert_allclose(g_infos.mean, e_states.mean, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g_infos.cov, e_states.cov, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(g_infos.n_components, 1)


def test_matches_numpy_gsf_with_number_limited_pruning():
    sc = jump_system()
    _, zs, ts = simulate(sc._replace(n_steps=25), jax.random.key(7))
    K = 12
    filt = build_gsf(sc.model, "ekf", PruneTop(num_out=K), capacity=K)
    _, infos = jax.jit(lambda z: run(filt, z))(zs)
    m = sc.model
    # the same system written in NumPy, with hand-derived Jacobians (independent of jax.jacfwd)
    f = lambda x, t: x / 2 + 25 * x / (1 + x**2) + 8 * np.cos(1.2 * (t - 1))  # noqa: E731
    f_jac = lambda x, t: np.atleast_2d(0.5 + 25 * (1 - x**2) / (1 + x**2) ** 2)  # noqa: E731
    h = lambda x, t: x**2 / 20 if t <= 80 else 3 * x - 4  # noqa: E731
    h_jac = lambda x, t: np.atleast_2d(x / 10 if t <= 80 else 3.0)  # noqa: E731
    ests, covs, _ = gsf_np.run_gsf(
        as_np(m.prior),
        np.asarray(zs),
        f,
        h,
        as_np(m.process_noise),
        as_np(m.measurement_noise),
        reducer=lambda mix: gsf_np.keep_heaviest(mix, K),
        f_jac=f_jac,
        h_jac=h_jac,
    )
    np.testing.assert_allclose(infos.mean, ests, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(infos.cov, covs, rtol=1e-8, atol=1e-8)


def test_nan_measurement_is_predict_only():
    model, F, H = linear_model()
    filt = build_gsf(model, "ekf", None, capacity=64)
    p, t1 = filt.params, StepInputs(t=jnp.int32(1))
    state = filt.init(p)
    pred = jax.jit(filt.predict)(p, state, t1)
    new, info = jax.jit(filt.update)(p, pred, jnp.array([jnp.nan]), t1)
    assert int(info.extra["n_updated"]) == int(gmm.n_active(pred.mixture))
    np.testing.assert_allclose(gmm.mean(new.mixture), gmm.mean(pred.mixture), rtol=1e-13)
    np.testing.assert_allclose(gmm.cov(new.mixture), gmm.cov(pred.mixture), rtol=1e-13)
    assert float(info.loglik) == 0.0
    assert np.all(np.isfinite(np.asarray(new.mixture.covs)))


def test_overflow_is_flagged_and_heaviest_kept():
    model, _, _ = linear_model()
    filt = build_gsf(model, "ekf", None, capacity=4)
    _, infos = run(filt, jnp.array([[0.1], [0.2]]))
    assert bool(infos.flags.overflow[0])  # 2 * 4 = 8 components > 4 slots
    np.testing.assert_array_equal(infos.n_components, 4)


def test_jit_equals_eager_and_vmap_equals_loop():
    sc = jump_system()._replace(n_steps=12)
    filt = build_gsf(sc.model, "ekf", PruneTop(num_out=8), capacity=8)
    zss = jnp.stack([simulate(sc, k)[1] for k in jax.random.split(jax.random.key(0), 2)])
    eager = [run(filt, z)[1].mean for z in zss]
    batched = jax.jit(jax.vmap(lambda z: run(filt, z)[1].mean))(zss)
    for i in range(2):
        np.testing.assert_allclose(batched[i], eager[i], rtol=1e-11, atol=1e-11)


def test_float32_runs_finite_and_close_to_float64():
    sc64 = jump_system()._replace(n_steps=15)
    sc32 = jump_system(dtype=jnp.float32)._replace(n_steps=15)
    _, zs, _ = simulate(sc64, jax.random.key(11))
    out = {}
    for name, sc in (("64", sc64), ("32", sc32)):
        filt = build_gsf(sc.model, "ekf", PruneTop(num_out=8), capacity=8)
        _, infos = jax.jit(lambda z: run(filt, z))(zs.astype(sc.model.prior.dtype))
        out[name] = infos
    assert out["32"].mean.dtype == jnp.float32
    assert np.all(np.isfinite(out["32"].mean))
    scale = np.abs(np.asarray(out["64"].mean)).max()
    np.testing.assert_allclose(out["32"].mean, out["64"].mean, atol=1e-3 * scale)


def test_bad_arguments_raise():
    model, _, _ = linear_model()
    with pytest.raises(ValueError, match="capacity"):
        build_gsf(model, "ekf", None, capacity=0)
    with pytest.raises(ValueError, match="local"):
        build_gsf(model, "nope", None, capacity=4)
    filt = build_gsf(model, "ekf", None, capacity=1)
    with pytest.raises(ValueError, match="prior"):
        filt.init(filt.params)  # two live prior components > capacity 1
    zs = jnp.zeros((3, 1))
    with pytest.raises(ValueError, match="prior"):  # its own prior is concrete under jit too
        jax.jit(lambda z: run(filt, z)[1].mean)(zs)
    # a traced prior cannot be counted at trace time: it is fitted (as documented), not refused
    assert jax.jit(lambda p: run(filt, zs, prior=p)[1].mean)(model.prior).shape == (3, 2)
    with pytest.raises(ValueError, match="reducer"):
        build_gsf(model, "ekf", lambda gm, key=None: (gm, None), capacity=4)


def test_stateful_reducer_state_is_carried_and_inherited():
    from gmjax.filters.gsf import inherit
    from gmjax.reduction.gmrcm import GMRCM, GMRCMState

    # children of slot i are i*n .. i*n+n-1, matching the (K, L) -> K*L flattening of predict/update
    np.testing.assert_array_equal(inherit(GMRCMState(jnp.array([3, 0, 1])), 2).low_count, [3, 3, 0, 0, 1, 1])
    sc = jump_system()._replace(n_steps=6)
    K = 8
    filt = build_gsf(sc.model, "ekf", GMRCM(capacity=K, newton_steps=0), capacity=K)
    state0 = filt.init(filt.params)
    assert state0.reducer_state.low_count.shape == (K,)
    _, zs, _ = simulate(sc, jax.random.key(4))
    states, infos = jax.jit(lambda z: run(filt, z))(zs)
    assert states.reducer_state.low_count.shape == (6, K)
    assert np.all(np.isfinite(infos.mean))
    # with a zero low-weight threshold no lineage is ever low, so every carried counter stays 0;
    # with the default 0.01 some of the 24 updated components per step are low and get counted
    never = build_gsf(sc.model, "ekf", GMRCM(capacity=K, newton_steps=0, weight_threshold=0.0), capacity=K)
    s0, _ = jax.jit(lambda z: run(never, z))(zs)
    np.testing.assert_array_equal(s0.reducer_state.low_count, 0)
    assert np.asarray(states.reducer_state.low_count).max() >= 1
    assert np.all(np.asarray(infos.n_components) <= K)


def test_underflowing_likelihoods_are_flagged_not_nan():
    # float32: an enormous measurement makes every component's log-likelihood -inf
    model, _, _ = linear_model(jnp.float32)
    filt = build_gsf(model, "ekf", PruneTop(num_out=8), capacity=8)
    p, t1 = filt.params, StepInputs(t=jnp.int32(1))
    pred = jax.jit(filt.predict)(p, filt.init(p), t1)
    new, info = jax.jit(filt.update)(p, pred, jnp.array([1e20], jnp.float32), t1)
    assert bool(info.flags.degenerate)
    assert np.all(np.isfinite(np.asarray(new.mixture.weights)))
    np.testing.assert_allclose(float(gmm.total_weight(new.mixture)), 1.0, rtol=1e-5)
    _, ok = jax.jit(filt.update)(p, pred, jnp.array([0.3], jnp.float32), t1)
    assert not bool(ok.flags.degenerate)


def _fd(fn, x, eps=1e-6):
    return (fn(x + eps) - fn(x - eps)) / (2 * eps)


def test_grad_of_loglik_wrt_noise_covariance_and_pruning_threshold_matches_finite_differences():
    """Parameters are data: d(sum loglik)/d(process-noise variance) and d/d(pruning threshold)."""
    from gmjax.reduction import PruneThreshold

    sc = jump_system()._replace(n_steps=10)
    _, zs, ts = simulate(sc, jax.random.key(2))
    filt = build_gsf(sc.model, "ekf", PruneThreshold(threshold=0.05, capacity=8), capacity=8, track_ise=False)
    p0 = filt.params

    def loglik_q(scale):
        q = p0.model.process_noise
        params = p0._replace(model=p0.model._replace(process_noise=q._replace(covs=q.covs * scale)))
        return jnp.sum(run(filt, zs, ts, params=params)[1].loglik)

    g = jax.jit(jax.grad(loglik_q))(1.0)
    assert np.isfinite(float(g)) and abs(float(g)) > 1e-6
    np.testing.assert_allclose(float(g), float(_fd(jax.jit(loglik_q), 1.0)), rtol=1e-5)

    # the hard threshold is piecewise constant: its gradient is exactly 0 and finite
    def loglik_thr(reducer0, thr):
        reducer = dataclasses.replace(reducer0, threshold=thr)
        return jnp.sum(run(filt, zs, ts, params=p0._replace(reducer=reducer))[1].loglik)

    gt = jax.jit(jax.grad(lambda t: loglik_thr(p0.reducer, t)))(0.05)
    assert float(gt) == 0.0
    # the reducer's own relaxation (soft gates, mode="soft") gives a real gradient that matches
    soft = PruneThreshold(threshold=0.05, capacity=8, temperature=0.02, mode="soft")
    gs = float(jax.jit(jax.grad(lambda t: loglik_thr(soft, t)))(0.05))
    fd = float(_fd(jax.jit(lambda t: loglik_thr(soft, t)), 0.05, 1e-6))
    assert np.isfinite(gs) and abs(gs) > 1e-6
    np.testing.assert_allclose(gs, fd, rtol=1e-5)


def test_vmap_over_parameter_sets_equals_loop():
    model, _, _ = linear_model()
    filt = build_gsf(model, "ekf", PruneTop(num_out=8), capacity=8, track_ise=False)
    zs = jnp.array([[0.4], [-0.3], [1.2], [0.1]])
    scales = jnp.array([0.5, 1.0, 2.0])

    def loglik(scale):
        r = filt.params.model.measurement_noise
        params = filt.params._replace(
            model=filt.params.model._replace(measurement_noise=r._replace(covs=r.covs * scale))
        )
        return run(filt, zs, params=params)[1].loglik

    batched = jax.jit(jax.vmap(loglik))(scales)
    for i, s in enumerate(scales):
        np.testing.assert_allclose(batched[i], loglik(s), rtol=1e-12)


def test_ise_diagnostic_is_opt_in_and_equals_the_closed_form_ise():
    """``track_ise`` adds ``extra["ise"]`` = metrics.ise(updated, reduced); without it the key is absent
    and a Monte Carlo study reports ``mean_ise`` as NaN (not tracked) rather than 0."""
    from gmjax import metrics
    from gmjax.filters.gsf import gs_predict, gs_update
    from gmjax.filters.local import local_filter_for
    from gmjax.montecarlo import monte_carlo

    sc = jump_system()
    sc = sc._replace(n_steps=3)
    red = PruneTop(num_out=6)
    _, zs, ts = simulate(sc, jax.random.key(1))
    plain = build_gsf(sc.model, "ekf", red, capacity=6)
    tracked = build_gsf(sc.model, "ekf", red, capacity=6, track_ise=True)
    s0 = tracked.init(tracked.params)
    inp = StepInputs(t=ts[0])

    def one_step(filt, s0):  # compiled (eager, the step's ops would compile one by one)
        step = lambda s: filt.update(filt.params, filt.predict(filt.params, s, inp), zs[0], inp)  # noqa: E731
        return jax.jit(step)(s0)

    state, info = one_step(tracked, s0)

    @jax.jit  # the same step by hand: the updated mixture and its reduction, then the closed-form ISE
    def ise_by_hand(s0, reduced):
        local = local_filter_for(sc.model, "ekf")
        pred = gs_predict(local, s0.mixture, inp, sc.model.process_noise)
        up = gs_update(local, pred, zs[0], inp, sc.model.measurement_noise).mixture
        return metrics.ise(up, reduced)

    np.testing.assert_allclose(info.extra["ise"], ise_by_hand(s0, state.mixture), rtol=1e-12)
    assert float(info.extra["ise"]) > 0
    _, plain_info = one_step(plain, plain.init(plain.params))
    assert "ise" not in plain_info.extra
    np.testing.assert_array_equal(plain_info.mean, info.mean)
    r_plain = monte_carlo(plain, sc, 4, jax.random.key(0), progress=False)
    r_tracked = monte_carlo(tracked, sc, 4, jax.random.key(0), progress=False)
    assert np.isnan(r_plain.mean_ise) and r_tracked.mean_ise > 0
    assert r_plain.armse == r_tracked.armse
