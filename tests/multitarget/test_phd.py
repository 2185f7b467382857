"""The GM-PHD filter of gmjax.multitarget: Kalman filter limit, closed forms, Stone Soup, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import multivariate_normal

from gmjax import multitarget as mt
from gmjax.filters import kalman_filter
from gmjax.filters import run as filters_run
from gmjax.filters.base import StepInputs
from gmjax.filters.local import local_filter_for
from gmjax.mixture import GaussianMixture
from gmjax.multitarget import phd
from gmjax.reduction import VoMa


def _gm(weights, means, covs, mask=None, dtype=jnp.float64):
    w = jnp.asarray(weights, dtype)
    mask = jnp.ones(w.shape, bool) if mask is None else jnp.asarray(mask, bool)
    return GaussianMixture.from_arrays(w, jnp.asarray(means, dtype), jnp.asarray(covs, dtype), mask)


def _no_birth(d=4):
    return _gm([0.0], np.zeros((1, d)), np.eye(d)[None], [False])


def _linear_parts(model):
    F = np.asarray(jax.jacfwd(model.f)(jnp.zeros(4), 0))
    H = np.asarray(jax.jacfwd(model.h)(jnp.zeros(4), 0))
    return F, H, np.asarray(model.process_noise.covs[0]), np.asarray(model.measurement_noise.covs[0])


@pytest.fixture(scope="module")
def linear():
    return mt.vo_ma_linear(n_steps=10, max_measurements=24)


def test_single_target_without_clutter_equals_kalman_filter(linear):
    """P_S = P_D = 1, no clutter, no birth, one target: the PHD is the Kalman filter (to 1e-10)."""
    model = linear.model
    F, H, Q, R = _linear_parts(model)
    m0, P0 = np.array([100.0, -50.0, 3.0, 4.0]), np.diag([100.0, 100.0, 25.0, 25.0])
    T = 12
    rng = np.random.default_rng(0)
    x, zs = m0.copy(), []
    for _ in range(T):
        x = F @ x + rng.multivariate_normal(np.zeros(4), Q)
        zs.append(H @ x + rng.multivariate_normal(np.zeros(2), R))
    zs = np.array(zs)
    padded = np.full((T, 3, 2), np.nan)
    padded[np.arange(T), rng.integers(0, 3, T)] = zs  # the one measurement in a random slot
    initial = _gm([1.0], m0[None], P0[None])
    f = mt.gm_phd(
        model,
        birth=_no_birth(),
        survival_prob=1.0,
        detection_prob=1.0,
        clutter_rate=0.0,
        clutter_density=1e-6,
        capacity=4,
        initial=initial,
    )
    states, infos = jax.jit(lambda z: mt.run(f, z))(jnp.asarray(padded))
    k_states, k_infos = filters_run(kalman_filter(F, H, Q, R, m0, P0), zs)
    slot = np.asarray(states.intensity.weights).argmax(-1)
    means = np.asarray(states.intensity.means)[np.arange(T), slot]
    covs = np.asarray(states.intensity.covs)[np.arange(T), slot]
    np.testing.assert_allclose(means, k_states.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(covs, k_states.cov, rtol=0, atol=1e-10)
    np.testing.assert_allclose(infos.extra["cardinality"], 1.0, atol=1e-12)
    assert np.all(np.asarray(infos.extra["n_estimates"]) == 1)
    est = np.asarray(infos.extra["estimates"])[:, 0]
    np.testing.assert_allclose(est, k_states.mean, atol=1e-10)
    # Poisson log-likelihood: -(lambda_c + P_D sum w) + log(q(z)) = KF loglik - 1
    np.testing.assert_allclose(infos.loglik, np.asarray(k_infos.loglik) - 1.0, atol=1e-10)


def test_expected_cardinality_closed_forms(linear):
    """No measurement: N = (1 - P_D)(P_S N_prev + N_birth); one measurement: eq 27 by hand."""
    model = linear.model
    p_s, p_d, lam, dens = 0.9, 0.6, 3.0, 2.5e-7
    birth = _gm(
        [0.1, 0.25], [[250.0, 250, 0, 0], [-250, -250, 0, 0]], np.stack([np.diag([100.0, 100, 25, 25])] * 2)
    )
    prev = _gm([0.7, 1.3], [[0.0, 0, 1, 1], [500, 0, -1, 0]], np.stack([np.eye(4) * 30] * 2))
    f = mt.gm_phd(
        model,
        birth=birth,
        survival_prob=p_s,
        detection_prob=p_d,
        clutter_rate=lam,
        clutter_density=dens,
        capacity=8,
        initial=prev,
    )
    t = StepInputs(t=jnp.asarray(1))
    state = jax.jit(f.predict)(f.params, f.init(f.params, None), t)
    np.testing.assert_allclose(jnp.sum(state.intensity.weights), p_s * 2.0 + 0.35, rtol=1e-14)
    update = jax.jit(f.update)  # compiled once for both measurement sets
    _, info = update(f.params, state, jnp.full((4, 2), jnp.nan), t)
    expected = (1 - p_d) * (p_s * 2.0 + 0.35)
    np.testing.assert_allclose(info.extra["cardinality"], expected, rtol=1e-13)
    np.testing.assert_allclose(info.extra["cardinality_reduced"], expected, rtol=1e-13)  # nothing pruned
    # one measurement: every component's detection weight by hand (SciPy densities)
    z = np.array([3.0, -2.0])
    _, info = update(f.params, state, jnp.asarray(np.vstack([z, np.full((3, 2), np.nan)])), t)
    F, H, Q, R = _linear_parts(model)
    w_pred = np.asarray(state.intensity.weights)
    q = np.array(
        [
            multivariate_normal(H @ np.asarray(m), H @ np.asarray(P) @ H.T + R).pdf(z)
            for m, P in zip(state.intensity.means, state.intensity.covs)
        ]
    )
    det = p_d * w_pred * q / (lam * dens + np.sum(p_d * w_pred * q))
    np.testing.assert_allclose(info.extra["cardinality"], (1 - p_d) * w_pred.sum() + det.sum(), rtol=1e-12)
    log_lik = -(lam + p_d * w_pred.sum()) + np.log(lam * dens + np.sum(p_d * w_pred * q))
    np.testing.assert_allclose(info.loglik, log_lik, rtol=1e-12)


def test_extraction_rounds_weights_and_soft_extraction_matches():
    w = [0.4, 0.6, 1.4, 1.6, 2.7, 0.0]
    gm = _gm(w, np.arange(12.0).reshape(6, 2), np.stack([np.eye(2)] * 6), [1, 1, 1, 1, 1, 0])
    est = mt.extract(gm, 0.5, max_estimates=10)
    assert int(est.n_estimates) == 0 + 1 + 1 + 2 + 3 and not bool(est.overflow)
    got = sorted(map(tuple, np.asarray(est.states)[np.asarray(est.mask)]))
    want = sorted([(2.0, 3.0), (4.0, 5.0), (6.0, 7.0), (6.0, 7.0), (8.0, 9.0), (8.0, 9.0), (8.0, 9.0)])
    assert got == want
    small = mt.extract(gm, 0.5, max_estimates=4)
    assert bool(small.overflow) and int(np.sum(small.mask)) == 4
    cand, e = mt.soft_estimates(gm, 0.5, 0.0, max_copies=3)
    assert float(jnp.sum(e)) == 7.0 and cand.shape == (18, 2)


def test_jit_eager_vmap_loop_and_float32(linear):
    f = mt.gm_phd(linear.model, **linear.filter_kwargs(), capacity=12, merge_capacity=48)
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    samples = jax.vmap(mt.simulate, (None, 0))(linear, keys)
    zs = samples.zs[:, :5]
    run_j = jax.jit(lambda z: mt.run(f, z))
    batched = jax.jit(jax.vmap(lambda z: mt.run(f, z)))(zs)
    for i in range(2):
        single = run_j(zs[i])
        for a, b in zip(jax.tree_util.tree_leaves(single), jax.tree_util.tree_leaves(batched)):
            np.testing.assert_allclose(a, b[i], rtol=1e-9, atol=1e-9)
    eager_states, eager_infos = mt.run(f, zs[0])
    np.testing.assert_allclose(
        eager_infos.extra["cardinality"], batched[1].extra["cardinality"][0], rtol=1e-10
    )
    # float32: the same filter in single precision tracks the float64 cardinality
    sc32 = mt.vo_ma_linear(n_steps=10, max_measurements=24, dtype=jnp.float32)
    f32 = mt.gm_phd(sc32.model, **sc32.filter_kwargs(), capacity=12, merge_capacity=48)
    _, infos32 = jax.jit(lambda z: mt.run(f32, z))(zs[0].astype(jnp.float32))
    assert infos32.extra["cardinality"].dtype == jnp.float32
    np.testing.assert_allclose(
        infos32.extra["cardinality"], eager_infos.extra["cardinality"], rtol=1e-3, atol=1e-4
    )


def test_agrees_with_stonesoup_gm_phd(linear):
    """Stone Soup's GM-PHD components on identical measurement sets.

    1. Step-exact: from the same posterior intensity, Stone Soup's predict + PHDUpdater and gmjax's
       predict + update give the same components (weights, means, covariances to 1e-9 relative).
    2. Each library's own recursion (own reducer) over the sequence: the conventions differ (Stone
       Soup caps a merged weight at 1, redistributes pruned weight, merges against the running merged
       component with ``d < U``; see references/phd_stonesoup.py), so the cardinality agrees
       to 0.05 per step (measured: <= 0.03 on this sequence) and the extracted sets coincide in size
       and to OSPA < 0.05 m.
    """
    pytest.importorskip("stonesoup")
    from references.phd_stonesoup import StoneSoupGMPHD
    from references.phd_stonesoup import extract as ss_extract

    model = linear.model
    F, H, Q, R = _linear_parts(model)
    sample = mt.simulate(linear, jax.random.PRNGKey(1))
    zs = np.asarray(sample.zs)[:8]
    assert not np.any(sample.overflow)
    f = mt.gm_phd(model, **linear.filter_kwargs(), capacity=30, merge_capacity=300)
    states, infos = jax.jit(lambda z: mt.run(f, z))(jnp.asarray(zs))
    b = linear.birth
    ss = StoneSoupGMPHD(
        F,
        Q,
        H,
        R,
        list(zip(np.asarray(b.weights), np.asarray(b.means), np.asarray(b.covs))),
        survival_prob=linear.survival_prob,
        detection_prob=linear.detection_prob,
        clutter_intensity=linear.clutter_rate * linear.clutter_density,
        max_components=30,
    )
    scans = [z[~np.isnan(z[:, 0])] for z in zs]
    lf = local_filter_for(model, "kf")
    step = jax.jit(
        lambda post, z, t: phd.update_intensity(
            lf, f.params, phd.predict_intensity(lf, f.params, post, t), z, t
        )
    )
    for k in range(1, len(scans)):
        post = jax.tree_util.tree_map(lambda a: a[k - 1], states.intensity)
        comps = [
            (float(w), np.asarray(m), np.asarray(P))
            for w, m, P, live in zip(post.weights, post.means, post.covs, post.mask)
            if live
        ]
        upd_ss, _ = ss.step(comps, scans[k], k + 1)
        u = step(post, jnp.asarray(zs[k]), jnp.asarray(k + 1)).intensity
        live = np.asarray(u.mask)
        order = np.argsort(-np.asarray(u.weights)[live], kind="stable")
        w_j = np.asarray(u.weights)[live][order]
        m_j, P_j = np.asarray(u.means)[live][order], np.asarray(u.covs)[live][order]
        order_s = np.argsort([-c[0] for c in upd_ss], kind="stable")
        assert len(w_j) == len(upd_ss)
        w_s = np.array([upd_ss[i][0] for i in order_s])
        # Stone Soup replaces exact-zero weights by machine epsilon; compare above that
        np.testing.assert_allclose(w_j, w_s, rtol=1e-9, atol=1e-15)
        big = w_s > 1e-8  # components distinguishable by weight (tiny ones may tie)
        m_s = np.array([upd_ss[i][1] for i in order_s])
        P_s = np.array([upd_ss[i][2] for i in order_s])
        np.testing.assert_allclose(m_j[big], m_s[big], rtol=1e-9, atol=1e-8)
        np.testing.assert_allclose(P_j[big], P_s[big], rtol=1e-8, atol=1e-8)
    reduced_ss = ss.run(scans)
    for k in range(len(scans)):
        card_s = sum(c[0] for c in reduced_ss[k])
        assert abs(float(infos.extra["cardinality_reduced"][k]) - card_s) < 0.05
        est_j = np.asarray(infos.extra["estimates"][k])[np.asarray(infos.extra["estimate_mask"][k])]
        est_s = ss_extract(reduced_ss[k])
        assert len(est_j) == len(est_s)
        if len(est_j):
            assert float(mt.ospa(est_j, est_s, c=100.0, p=1.0)) < 0.05


def test_relaxed_vo_ma_at_zero_temperature_is_vo_ma():
    rng = np.random.default_rng(4)
    K = 24
    centres = rng.normal(size=(4, 2)) * 20
    means = centres[rng.integers(0, 4, K)] + rng.normal(size=(K, 2)) * 1.5
    covs = np.stack([np.eye(2) * s for s in rng.uniform(1, 3, K)])
    w = rng.uniform(0, 0.5, K) * (rng.random(K) > 0.2) + 1e-7
    gm = _gm(w, means, covs, rng.random(K) > 0.1)
    hard, info_h = jax.jit(lambda g: VoMa(1e-4, 4.0, max_components=6)(g))(gm)  # (eager: op by op)
    soft, info_s = jax.jit(lambda g: mt.RelaxedVoMa(1e-4, 4.0, max_components=6)(g))(gm)
    total = float(jnp.sum(jnp.where(gm.mask, gm.weights, 0.0)))
    scale = (total - float(info_h.pruned_mass)) / total  # VoMa rescales to the input total; the PHD does not
    oh = np.argsort(-np.asarray(hard.weights))[:6]
    assert int(jnp.sum(hard.mask)) <= 6
    os_ = np.argsort(-np.asarray(soft.weights))
    np.testing.assert_allclose(
        np.asarray(soft.weights)[os_], np.asarray(hard.weights)[oh] * scale, rtol=1e-12
    )
    np.testing.assert_allclose(np.asarray(soft.means)[os_], np.asarray(hard.means)[oh], atol=1e-12)
    np.testing.assert_allclose(np.asarray(soft.covs)[os_], np.asarray(hard.covs)[oh], atol=1e-12)
    np.testing.assert_allclose(info_s.pruned_mass, info_h.pruned_mass, rtol=1e-10)


def test_gradient_of_mean_gospa_wrt_thresholds_matches_finite_differences(linear):
    """d mean-GOSPA / d (T, U) through a vmapped Monte Carlo study with a relaxed reduction and extraction."""
    sc = mt.vo_ma_linear(n_steps=5, max_measurements=16, clutter_rate=5.0)
    keys = jax.random.split(jax.random.PRNGKey(7), 2)
    samples = jax.jit(jax.vmap(lambda k: mt.simulate(sc, k)))(keys)
    base = mt.gm_phd(
        sc.model,
        **sc.filter_kwargs(),
        capacity=10,
        merge_capacity=40,
        reducer=mt.RelaxedVoMa(1e-3, 4.0, 5e-4, 1.0, max_components=10),
    )

    def loss(log_thresholds):
        T, U = jnp.exp(log_thresholds)
        params = base.params._replace(reducer=mt.RelaxedVoMa(T, U, 5e-4, 1.0, max_components=10))

        def one(zs, truth, alive):
            states, _ = mt.run(base, zs, params=params)

            def score(post, x, a):
                cand, e = mt.soft_estimates(post, 0.5, 0.05, max_copies=2)
                return mt.soft_gospa(cand[:, :2], x[:, :2], e, a, c=50.0, p=2.0).distance ** 2

            return jnp.mean(jax.vmap(score)(states.intensity, truth, alive))

        return jnp.mean(jax.vmap(one)(samples.zs, samples.states, samples.alive))

    x0 = jnp.log(jnp.array([1e-3, 4.0]))
    val, grad = jax.jit(jax.value_and_grad(loss))(x0)
    assert np.all(np.isfinite(grad)) and np.any(np.abs(grad) > 0)
    f = jax.jit(loss)
    h = 1e-4
    fd = np.array([(f(x0.at[i].add(h)) - f(x0.at[i].add(-h))) / (2 * h) for i in range(2)])
    np.testing.assert_allclose(grad, fd, rtol=2e-3, atol=1e-6 * abs(float(val)))


def test_simulation_counts_and_overflow_flag(linear):
    keys = jax.random.split(jax.random.PRNGKey(0), 200)
    s = jax.jit(jax.vmap(lambda k: mt.simulate(linear, k)))(keys)
    n_rows = np.sum(~np.isnan(np.asarray(s.zs)[..., 0]), -1)
    n_det = np.sum(np.asarray(s.detected), -1)
    n_valid = n_det + np.asarray(s.n_clutter)
    np.testing.assert_array_equal(n_rows, np.minimum(n_valid, linear.max_measurements))
    np.testing.assert_array_equal(np.asarray(s.overflow), n_valid > linear.max_measurements)
    # clutter ~ Poisson(10) and detections ~ Bernoulli(P_D) per live target: means within 4 standard errors
    nc = np.asarray(s.n_clutter).ravel()
    assert abs(nc.mean() - 10.0) < 4 * np.sqrt(10.0 / nc.size)
    alive = np.asarray(s.alive)
    rate = np.asarray(s.detected)[alive].mean()
    assert abs(rate - 0.98) < 4 * np.sqrt(0.98 * 0.02 / alive.sum())
    assert np.all(np.asarray(s.detected) <= alive)
    # clutter inside the region
    pts = np.asarray(s.zs)[..., 0]
    assert np.nanmax(np.abs(pts)) < 1000 + 60  # detections can lie a few sigma outside
    # a scan capacity smaller than the set: flagged, detections kept first
    tight = linear._replace(max_measurements=3)
    st = jax.jit(lambda k: mt.simulate(tight, k))(jax.random.PRNGKey(5))
    n_valid = np.sum(np.asarray(st.detected), -1) + np.asarray(st.n_clutter)
    np.testing.assert_array_equal(np.asarray(st.overflow), n_valid > 3)
    assert np.any(st.overflow)


@pytest.mark.parametrize("local", ["ekf", pytest.param("ukf", marks=pytest.mark.slow)])
def test_range_bearing_nonlinear_components_track(local):
    """EKF / UKF components on the range-bearing scenario: a smoke check against the truth.

    After the first births are confirmed (step 5 on), the mean OSPA (c = 100 m, p = 1) stays below
    25 m and the mean absolute cardinality error below 0.5 (the measurement noise is ~5 m in range and
    ~5 m cross-range; a lost or doubled target costs 100 m / n).
    """
    sc = mt.range_bearing(n_steps=30, max_measurements=20)
    s = mt.simulate(sc, jax.random.PRNGKey(2))
    f = mt.gm_phd(sc.model, **sc.filter_kwargs(), capacity=16, merge_capacity=64, local=local)
    _, infos = jax.jit(lambda z: mt.run(f, z))(s.zs)
    est = infos.extra["estimates"][..., :2]
    o = jax.vmap(lambda e, em, x, a: mt.ospa(e, x, em, a, c=100.0, p=1.0))(
        est, infos.extra["estimate_mask"], s.states[..., :2], s.alive
    )
    card_err = np.abs(np.asarray(infos.extra["n_estimates"]) - np.asarray(s.alive).sum(-1))
    assert float(np.mean(o[5:])) < 25.0
    assert float(np.mean(card_err[5:])) < 0.5


def test_bad_inputs_raise(linear):
    kw = linear.filter_kwargs()
    with pytest.raises(ValueError, match="detection_prob"):
        mt.gm_phd(linear.model, **{**kw, "detection_prob": 1.5})
    with pytest.raises(ValueError, match="clutter_density"):
        mt.gm_phd(linear.model, **{**kw, "clutter_density": 0.0})
    with pytest.raises(ValueError, match="local"):
        mt.gm_phd(linear.model, **kw, local="nope")
    with pytest.raises(ValueError, match="birth"):
        mt.gm_phd(linear.model, **{**kw, "birth": _no_birth(2)})
    f = mt.gm_phd(linear.model, **kw, capacity=4)
    with pytest.raises(ValueError, match="zs"):
        mt.run(f, jnp.zeros((3, 2)))
