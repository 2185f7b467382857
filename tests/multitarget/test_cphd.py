"""The GM-CPHD filter of gmjax.multitarget: NumPy reference, brute force, ESFs, PHD limit, batching, gradients."""

import math
import re
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import multitarget as mt
from gmjax.filters.local import local_filter_for
from gmjax.mixture import GaussianMixture
from gmjax.multitarget import cphd, phd
from references import cphd_np

DOCS_PAGE = Path(__file__).resolve().parents[2] / "docs" / "reproductions" / "phd.md"


def _gm(weights, means, covs, mask=None, dtype=jnp.float64):
    w = jnp.asarray(weights, dtype)
    mask = jnp.ones(w.shape, bool) if mask is None else jnp.asarray(mask, bool)
    return GaussianMixture.from_arrays(w, jnp.asarray(means, dtype), jnp.asarray(covs, dtype), mask)


def _linear_parts(model):
    F = np.asarray(jax.jacfwd(model.f)(jnp.zeros(4), 0))
    H = np.asarray(jax.jacfwd(model.h)(jnp.zeros(4), 0))
    return F, H, np.asarray(model.process_noise.covs[0]), np.asarray(model.measurement_noise.covs[0])


def _live(zs):
    return zs[~np.isnan(zs[:, 0])]


def _by_mean(m):
    """Row order sorting components by their means (robust to exactly tied weights)."""
    return np.lexsort(m.T[::-1])


@pytest.fixture(scope="module")
def small():
    """Vo & Ma's linear scenario, 8 steps, clutter 4 per scan, 12-row scans; one simulated run."""
    sc = mt.vo_ma_linear(n_steps=8, max_measurements=12, clutter_rate=4.0)
    sample = mt.simulate(sc, jax.random.PRNGKey(11))
    assert not np.any(sample.overflow)
    return sc, sample


# capacities of the shared filter: every updated component reaches the reducer (no truncation)
CAP, N_MAX = 20, 12


@pytest.fixture(scope="module")
def kf_update():
    """``update_cphd`` with KF components of the Vo & Ma model, compiled once for the module."""
    sc = mt.vo_ma_linear(n_steps=2)
    lf = local_filter_for(sc.model, "kf")
    return sc, jax.jit(partial(cphd.update_cphd, lf)), jax.jit(partial(phd.update_intensity, lf))


@pytest.fixture(scope="module")
def small_filter(small):
    """The filter of the step-exact test and ``run(zs, params, init_state)``, compiled once for the module
    (the flag tests reuse the program with other inputs, parameters and initial states)."""
    sc, _ = small
    merge = (CAP + 2) * (1 + sc.max_measurements)
    f = cphd.gm_cphd(sc.model, **sc.filter_kwargs(), n_max=N_MAX, capacity=CAP, merge_capacity=merge)
    return f, jax.jit(lambda z, params, init: mt.run(f, z, params=params, init_state=init))


# ----------------------------------------------------------------------------- ESFs and the cardinality


def _exact_esf(ints):
    """Vieta's recursion over Python ints (exact)."""
    e = [1] + [0] * len(ints)
    for i, x in enumerate(ints):
        for j in range(i + 1, 0, -1):
            e[j] += x * e[j - 1]
    return e


def test_log_esf_matches_numpy_poly_direct_expansion_and_leave_one_out():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.1, 3.0, 9)
    mask = np.ones(9, bool)
    mask[[2, 6]] = False  # padded slots: the factor (1 + 0 t)
    le = np.asarray(cphd.log_esf(jnp.log(x), mask))
    coeffs = np.poly(-x[mask])  # prod (t + x_i) = sum_j e_j t^{n-j}
    np.testing.assert_allclose(np.exp(le[:8]), coeffs, rtol=1e-13)
    assert np.all(np.isneginf(le[8:]))
    np.testing.assert_allclose(np.exp(le[:8]), cphd_np.esf(x[mask]), rtol=1e-13)
    # e_2 by direct expansion over pairs
    xm = x[mask]
    e2 = sum(xm[a] * xm[b] for a in range(len(xm)) for b in range(a + 1, len(xm)))
    np.testing.assert_allclose(np.exp(le[2]), e2, rtol=1e-13)
    # one recursion per left-out slot; a padded slot's row is the full set's
    loo = np.asarray(cphd.log_esf_leave_one_out(jnp.log(x), mask))
    for i in range(9):
        keep = mask & (np.arange(9) != i)
        np.testing.assert_allclose(
            np.exp(loo[i]), np.r_[cphd_np.esf(x[keep]), np.zeros(9 - keep.sum())], rtol=1e-13
        )


def test_log_esf_large_sets_do_not_overflow():
    """M = 300 values up to 1e6: e_j up to ~1e1700 (far beyond float64), exact in the log domain."""
    rng = np.random.default_rng(1)
    ints = [int(v) for v in rng.integers(1, 10**6, 300)]
    exact = _exact_esf(ints)
    want = np.array([math.log(e) for e in exact])
    got = np.asarray(jax.jit(cphd.log_esf)(jnp.log(jnp.asarray(ints, jnp.float64))))
    assert want[-1] > 3000 and np.all(np.isfinite(got))
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-9)
    # float32, M = 100 values ~ 1e3 (e_50 ~ 1e179): finite and close to float64
    x = rng.uniform(500.0, 2000.0, 100)
    got32 = np.asarray(cphd.log_esf(jnp.log(jnp.asarray(x, jnp.float32))))
    got64 = np.asarray(cphd.log_esf(jnp.log(jnp.asarray(x))))
    assert got32.dtype == np.float32 and np.all(np.isfinite(got32))
    np.testing.assert_allclose(got32, got64, rtol=2e-6, atol=1e-3)


@pytest.mark.parametrize("p_s, birth_mean", [(0.9, 0.35), (1.0, 0.0), (0.6, 2.5)])
def test_cardinality_prediction_matches_reference(p_s, birth_mean):
    rng = np.random.default_rng(2)
    p = rng.dirichlet(np.ones(9))
    p[7:] = 0.0  # zeros: -inf in the log domain
    p /= p.sum()
    log_p = jnp.where(p > 0, jnp.log(jnp.where(p > 0, p, 1.0)), -jnp.inf)
    got, tail = cphd.predict_cardinality(log_p, p_s, birth_mean)
    want, want_tail = cphd_np.predict_cardinality(p, p_s, birth_mean)
    np.testing.assert_allclose(np.exp(got), want, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(tail, want_tail, atol=1e-14)
    if p_s == 1.0 and birth_mean == 0.0:
        np.testing.assert_allclose(np.exp(got), p, atol=1e-15)


# ----------------------------------------------------------------------------- the update


def _tiny_prediction(dtype=jnp.float64):
    """Three predicted components and a non-Poisson cardinality over 0..5."""
    covs = np.stack(
        [np.diag([200.0, 150.0, 20.0, 20.0]), np.diag([120.0, 300.0, 10.0, 30.0]), np.eye(4) * 80.0]
    )
    pred = _gm([0.8, 0.5, 0.3], [[0.0, 0, 1, 1], [40.0, -20, 0, 2], [300.0, 300, 0, 0]], covs, dtype=dtype)
    p = np.array([0.05, 0.2, 0.3, 0.25, 0.15, 0.05])
    return pred, p


@pytest.mark.parametrize(
    "p_d, lam, n_z", [(0.7, 1.5, 3), (1.0, 0.8, 2), (0.6, 0.0, 3), (0.9, 2.0, 0)], ids=str
)
def test_update_matches_brute_force_enumeration(kf_update, p_d, lam, n_z):
    """Cardinality, intensity weights and log-likelihood of one update against the exact Bayes update of
    the i.i.d. cluster prior by enumeration of every association hypothesis (references/cphd_np.py)."""
    sc, update, _ = kf_update
    model = sc.model
    F, H, Q, R = _linear_parts(model)
    pred, p = _tiny_prediction()
    c = 1.0 / 200.0**2
    Z = np.array([[5.0, 3.0], [35.0, -10.0], [-60.0, 80.0]])[:n_z]
    zs = np.full((4, 2), np.nan)
    zs[[0, 2, 3][:n_z]] = Z  # measurements in scattered rows of a padded set
    f = cphd.gm_cphd(model, birth=sc.birth, detection_prob=p_d, clutter_rate=lam, clutter_density=c, n_max=5)
    upd = update(f.params, pred, jnp.log(jnp.asarray(p)), jnp.asarray(zs), jnp.asarray(1))
    w, m, P = (np.asarray(a) for a in (pred.weights, pred.means, pred.covs))
    p_post, missed, detected, loglik = cphd_np.brute_force_update(w, m, P, p, Z, H, R, p_d, lam, c)
    np.testing.assert_allclose(np.exp(upd.log_cardinality), p_post, rtol=1e-11, atol=1e-14)
    weights = np.asarray(upd.intensity.weights)
    np.testing.assert_allclose(weights[:3], missed, rtol=1e-11, atol=1e-14)
    det = weights[3:].reshape(4, 3)[[0, 2, 3][:n_z]].T  # (K, n_z)
    np.testing.assert_allclose(det, detected, rtol=1e-11, atol=1e-14)
    np.testing.assert_allclose(upd.loglik, loglik, rtol=1e-12)
    # the intensity's mass is the posterior mean cardinality (a property of the CPHD update)
    n = np.arange(6)
    np.testing.assert_allclose(weights.sum(), n @ p_post, rtol=1e-12)
    assert not bool(upd.degenerate)


def test_update_with_a_hundred_measurements_and_n_max_100(kf_update):
    """M = 100 measurements, N_max = 100, lambda_c = 80, a broad predicted cardinality: the largest term
    of Upsilon is ~1e159 (far beyond float32's range in the linear domain); in the log domain the update is
    finite in float64 and float32, float32 agrees with float64, and the intensity's mass is the mean
    cardinality."""
    sc, update, _ = kf_update
    pred, _ = _tiny_prediction()
    rng = np.random.default_rng(3)
    near = np.asarray(pred.means)[:, :2] + rng.normal(0.0, 10.0, (3, 2))
    zs = np.vstack([near, rng.uniform(-1000.0, 1000.0, (97, 2))])
    f = cphd.gm_cphd(sc.model, **{**sc.filter_kwargs(), "clutter_rate": 80.0}, n_max=100)
    log_p = cphd.poisson_log_pmf(100, 30.0)
    t = jnp.asarray(1)
    upd64 = update(f.params, pred, log_p, jnp.asarray(zs), t)
    sc32 = mt.vo_ma_linear(n_steps=2, dtype=jnp.float32)
    f32 = cphd.gm_cphd(sc32.model, **{**sc32.filter_kwargs(), "clutter_rate": 80.0}, n_max=100)
    pred32, params32 = _tiny_prediction(jnp.float32)[0], f32.params
    update32 = jax.jit(partial(cphd.update_cphd, local_filter_for(sc32.model, "kf")))
    upd32 = update32(params32, pred32, log_p.astype(jnp.float32), jnp.asarray(zs, jnp.float32), t)
    assert upd32.intensity.weights.dtype == jnp.float32
    for upd, rtol in ((upd64, 1e-10), (upd32, 2e-4)):
        assert not bool(upd.degenerate) and np.isfinite(float(upd.loglik))
        assert np.all(np.isfinite(upd.intensity.weights)) and np.all(np.isfinite(np.exp(upd.log_cardinality)))
        mean, _ = cphd.cardinality_moments(upd.log_cardinality)
        np.testing.assert_allclose(jnp.sum(upd.intensity.weights), mean, rtol=rtol)
    np.testing.assert_allclose(np.exp(upd32.log_cardinality), np.exp(upd64.log_cardinality), atol=1e-5)
    np.testing.assert_allclose(upd32.intensity.weights, upd64.intensity.weights, rtol=2e-3, atol=1e-6)
    np.testing.assert_allclose(upd32.loglik, upd64.loglik, rtol=1e-5)


def test_poisson_cardinality_gives_the_phd_update(kf_update):
    """With a Poisson predicted cardinality of mean 1^T w (N_max large), the CPHD intensity update and
    log-likelihood are the GM-PHD's (the Poisson i.i.d. cluster process is the Poisson process)."""
    sc, update, phd_update = kf_update
    pred, _ = _tiny_prediction()
    f = cphd.gm_cphd(sc.model, **sc.filter_kwargs(), n_max=60)
    zs = jnp.asarray([[5.0, 3.0], [np.nan, np.nan], [35.0, -10.0], [600.0, -400.0]])
    log_p = cphd.poisson_log_pmf(60, jnp.sum(pred.weights))
    t = jnp.asarray(1)
    upd = update(f.params, pred, log_p, zs, t)
    ref = phd_update(f.params.as_phd(), pred, zs, t)
    np.testing.assert_allclose(upd.intensity.weights, ref.intensity.weights, rtol=1e-10, atol=1e-16)
    np.testing.assert_allclose(upd.intensity.means, ref.intensity.means, rtol=1e-12)
    np.testing.assert_allclose(upd.loglik, ref.loglik, rtol=1e-11)


def test_step_exact_against_numpy_reference(small, small_filter):
    """Over the 8 steps of a simulated run, gmjax's GM-CPHD (jit, log domain) and the plain NumPy loop
    written from the paper (linear-domain Vieta ESFs, Upsilon with (1^T w)^{j+u}) agree to 1e-9 in every
    weight, mean, covariance, cardinality probability, estimate and log-likelihood."""
    sc, sample = small
    f, run = small_filter
    states, infos = run(sample.zs, f.params, f.init(f.params))
    F, H, Q, R = _linear_parts(sc.model)
    b = sc.birth
    ref = cphd_np.run(
        [_live(z) for z in np.asarray(sample.zs)],
        F,
        Q,
        H,
        R,
        (np.asarray(b.weights), np.asarray(b.means), np.asarray(b.covs)),
        p_s=sc.survival_prob,
        p_d=sc.detection_prob,
        lam=sc.clutter_rate,
        c=sc.clutter_density,
        n_max=N_MAX,
        T=1e-5,
        U=4.0,
        J_max=CAP,
    )
    assert not np.any(infos.flags.any())
    for k, r in enumerate(ref):
        post = jax.tree_util.tree_map(lambda a: np.asarray(a[k]), states.intensity)
        live = post.mask
        assert live.sum() == len(r["w"])
        o, o_r = _by_mean(post.means[live]), _by_mean(r["m"])
        np.testing.assert_allclose(post.weights[live][o], r["w"][o_r], rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(post.means[live][o], r["m"][o_r], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(post.covs[live][o], r["P"][o_r], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(np.asarray(states.cardinality[k]), r["p"], rtol=1e-9, atol=1e-13)
        np.testing.assert_allclose(infos.extra["cardinality_tail"][k], r["tail"], atol=1e-13)
        np.testing.assert_allclose(infos.loglik[k], r["loglik"], rtol=1e-10)
        np.testing.assert_allclose(infos.extra["intensity_mass"][k], r["w_updated"].sum(), rtol=1e-9)
        est = np.asarray(infos.extra["estimates"][k])[np.asarray(infos.extra["estimate_mask"][k])]
        assert len(est) == len(r["estimates"])
        np.testing.assert_allclose(est[_by_mean(est)], r["estimates"][_by_mean(r["estimates"])], rtol=1e-9)
    # and it tracked the run: the MAP cardinality is never off by more than one target
    assert np.all(np.abs(infos.extra["cardinality_map"] - np.asarray(sample.alive).sum(-1)) <= 1)


# ----------------------------------------------------------------------------- batching, dtypes, gradients


def test_jit_equals_eager_and_vmap_equals_loop(kf_update):
    """The update (ESFs, Upsilon, weights) eager (op by op) == jit, and vmapped over measurement sets and
    cardinality distributions == one call each (the whole filter vmapped over runs: the slow test below)."""
    sc, update, _ = kf_update
    pred, p = _tiny_prediction()
    f = cphd.gm_cphd(sc.model, **sc.filter_kwargs(), n_max=5)
    zs = jnp.asarray([[5.0, 3.0], [np.nan, np.nan], [35.0, -10.0], [600.0, -400.0]])
    t = jnp.asarray(1)
    log_p = jnp.log(jnp.asarray(p))
    eager = cphd.update_cphd(local_filter_for(sc.model, "kf"), f.params, pred, log_p, zs, t)
    jitted = update(f.params, pred, log_p, zs, t)
    for a, b in zip(jax.tree_util.tree_leaves(eager), jax.tree_util.tree_leaves(jitted)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    zs2 = jnp.stack([zs, zs[::-1] + 1.0])
    log_p2 = jnp.stack([log_p, cphd.poisson_log_pmf(5, 1.2)])
    batched = jax.jit(jax.vmap(update, (None, None, 0, 0, None)))(f.params, pred, log_p2, zs2, t)
    for i in range(2):
        single = update(f.params, pred, log_p2[i], zs2[i], t)
        for a, b in zip(jax.tree_util.tree_leaves(single), jax.tree_util.tree_leaves(batched)):
            np.testing.assert_allclose(a, b[i], rtol=1e-12, atol=1e-14)


@pytest.mark.slow
def test_vmap_over_runs_equals_loop(small, small_filter):
    sc, sample = small
    f, run = small_filter
    zs = jnp.stack([sample.zs, mt.simulate(sc, jax.random.PRNGKey(12)).zs])
    batched = jax.jit(jax.vmap(lambda z: mt.run(f, z)))(zs)
    for i in range(2):
        single = run(zs[i], f.params, f.init(f.params))
        for a, b in zip(jax.tree_util.tree_leaves(single), jax.tree_util.tree_leaves(batched)):
            np.testing.assert_allclose(a, b[i], rtol=1e-9, atol=1e-12)


def test_float32_runs_and_tracks_float64(small, small_filter):
    sc, sample = small
    f, run = small_filter
    _, infos64 = run(sample.zs, f.params, f.init(f.params))
    sc32 = mt.vo_ma_linear(n_steps=8, max_measurements=12, clutter_rate=4.0, dtype=jnp.float32)
    merge = (CAP + 2) * (1 + sc.max_measurements)
    f32 = cphd.gm_cphd(sc32.model, **sc32.filter_kwargs(), n_max=N_MAX, capacity=CAP, merge_capacity=merge)
    states32, infos32 = jax.jit(lambda z: mt.run(f32, z))(sample.zs.astype(jnp.float32))
    assert states32.log_cardinality.dtype == jnp.float32 and infos32.extra["cardinality"].dtype == jnp.float32
    assert np.all(np.isfinite(infos32.extra["cardinality"])) and np.all(np.isfinite(infos32.loglik))
    np.testing.assert_allclose(
        infos32.extra["cardinality"], infos64.extra["cardinality"], rtol=1e-4, atol=1e-4
    )
    np.testing.assert_allclose(infos32.loglik, infos64.loglik, rtol=1e-4)
    np.testing.assert_array_equal(infos32.extra["cardinality_map"], infos64.extra["cardinality_map"])


def test_gradient_of_the_update_wrt_clutter_rate_and_detection_prob_matches_central_differences():
    """d/d(lambda_c, P_D) of one prediction + update's log-likelihood, intensity mass and mean cardinality
    (the CPHD-specific path: cardinality prediction, ESFs, Upsilon, weights), against central differences."""
    sc = mt.vo_ma_linear(n_steps=2)
    pred, p = _tiny_prediction()
    f = cphd.gm_cphd(sc.model, **sc.filter_kwargs(), n_max=8)
    lf = local_filter_for(sc.model, "kf")
    zs = jnp.asarray([[5.0, 3.0], [np.nan, np.nan], [35.0, -10.0], [600.0, -400.0]])
    log_p = jnp.log(jnp.asarray(np.r_[p, 0.0, 0.0, 0.0]))

    def loss(theta):
        params = f.params._replace(clutter_rate=theta[0], detection_prob=theta[1])
        log_pred, _ = cphd.predict_cardinality(log_p, params.survival_prob, 0.2)
        upd = cphd.update_cphd(lf, params, pred, log_pred, zs, jnp.asarray(1))
        mean, var = cphd.cardinality_moments(upd.log_cardinality)
        return upd.loglik + jnp.sum(upd.intensity.weights) + mean + var

    value = jax.jit(jax.value_and_grad(loss))  # one program for the gradient and the differences
    theta = jnp.array([4.0, 0.9])
    val, grad = value(theta)
    assert np.isfinite(val) and np.all(np.isfinite(grad)) and np.all(np.abs(grad) > 0)
    h = 1e-6
    fd = np.array(
        [(value(theta.at[i].add(h))[0] - value(theta.at[i].add(-h))[0]) / (2 * h) for i in range(2)]
    )
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


@pytest.mark.slow
def test_gradient_wrt_clutter_rate_and_detection_prob_matches_central_differences(small):
    """d/d(lambda_c, P_D) of the summed log-likelihood plus the summed mean cardinality over 4 steps."""
    sc, sample = small
    f = cphd.gm_cphd(sc.model, **sc.filter_kwargs(), n_max=8, capacity=10, merge_capacity=40)
    zs = sample.zs[:4]

    def loss(theta):
        params = f.params._replace(clutter_rate=theta[0], detection_prob=theta[1])
        _, infos = mt.run(f, zs, params=params)
        return jnp.sum(infos.loglik) + jnp.sum(infos.extra["cardinality"])

    theta = jnp.array([4.0, 0.9])
    value = jax.jit(jax.value_and_grad(loss))  # one program for the gradient and the differences
    val, grad = value(theta)
    assert np.isfinite(val) and np.all(np.isfinite(grad)) and np.all(np.abs(grad) > 0)
    h = 1e-6
    fd = np.array(
        [(value(theta.at[i].add(h))[0] - value(theta.at[i].add(-h))[0]) / (2 * h) for i in range(2)]
    )
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


# ----------------------------------------------------------------------------- flags and errors


def test_flags_tail_degenerate_and_nonfinite_measurements(small, small_filter):
    """The shared program with other initial states, parameters and measurements (no recompilation)."""
    _, sample = small
    f, run = small_filter
    dtype = jnp.float64
    # N_max targets and births: the first prediction cuts the mass above N_max and says so
    prior = _gm([6.0, 6.0], [[250.0, 250, 0, 0], [-250, -250, 0, 0]], np.stack([np.eye(4) * 50] * 2))
    full = f.init(f.params, prior)
    full = full._replace(log_cardinality=jnp.log(jnp.eye(N_MAX + 1, dtype=dtype)[N_MAX]))
    _, infos = run(sample.zs, f.params, full)
    assert bool(infos.flags.overflow[0]) and float(infos.extra["cardinality_tail"][0]) > 1e-3
    assert np.all(np.isfinite(infos.loglik)) and not np.any(infos.flags.degenerate)
    # an impossible set: no clutter, no target (empty intensity, no births) and one measurement
    params = f.params._replace(
        clutter_rate=jnp.asarray(0.0, dtype), birth=f.params.birth._replace(weights=jnp.zeros(2, dtype))
    )
    zs = jnp.full_like(sample.zs, jnp.nan).at[0, 3].set(jnp.asarray([10.0, -20.0]))
    states, infos = run(zs, params, f.init(params))
    assert bool(infos.flags.degenerate[0]) and np.isneginf(float(infos.loglik[0]))
    assert not np.any(infos.flags.degenerate[1:]) and np.all(infos.loglik[1:] == 0.0)
    assert np.all(np.isfinite(states.intensity.weights)) and np.all(np.isfinite(infos.mean))
    np.testing.assert_allclose(states.cardinality[:, 0], 1.0)
    # a row with an infinite entry is ignored and flagged
    _, clean = run(sample.zs, f.params, f.init(f.params))
    _, flagged = run(sample.zs.at[0, -1, 0].set(jnp.inf), f.params, f.init(f.params))
    assert bool(flagged.flags.nonfinite_measurement[0]) and not np.any(clean.flags.nonfinite_measurement)
    np.testing.assert_allclose(flagged.extra["cardinality"], clean.extra["cardinality"], rtol=1e-14)


def test_bad_inputs_raise():
    sc = mt.vo_ma_linear(n_steps=2)
    kw = sc.filter_kwargs()
    for n_max in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="n_max"):
            cphd.gm_cphd(sc.model, **kw, n_max=n_max)
    for name, value in [
        ("detection_prob", 0.0),
        ("detection_prob", 1.5),
        ("survival_prob", 0.0),
        ("survival_prob", -0.1),
    ]:
        with pytest.raises(ValueError, match=name):
            cphd.gm_cphd(sc.model, **{**kw, name: value})
    with pytest.raises(ValueError, match="clutter_rate"):
        cphd.gm_cphd(sc.model, **{**kw, "clutter_rate": -1.0})
    with pytest.raises(ValueError, match="clutter_density"):
        cphd.gm_cphd(sc.model, **{**kw, "clutter_density": 0.0})
    with pytest.raises(ValueError, match="initial_cardinality"):
        cphd.gm_cphd(sc.model, **kw, n_max=3, initial_cardinality=[0.5, 0.5])
    with pytest.raises(ValueError, match="initial_cardinality"):
        cphd.gm_cphd(sc.model, **kw, n_max=2, initial_cardinality=[0.5, 0.4, 0.4])
    with pytest.raises(ValueError, match="local"):
        cphd.gm_cphd(sc.model, **kw, local="nope")
    f = cphd.gm_cphd(sc.model, **kw, n_max=3, capacity=4)
    with pytest.raises(ValueError, match="zs"):
        mt.run(f, jnp.zeros((3, 2)))


# ----------------------------------------------------------------------------- documentation


# the code block of the GM-CPHD section of docs/reproductions/phd.md, verbatim (that page is not run by
# tests/test_docs_examples.py, so it runs here; the test checks the page still shows this code)
DOCS_SNIPPET = """\
import jax
from gmjax import multitarget as mt

scenario = mt.vo_ma_linear(n_steps=20, max_measurements=24)
sample = mt.simulate(scenario, jax.random.PRNGKey(0))
cphd = mt.gm_cphd(scenario.model, **scenario.filter_kwargs(), n_max=20, capacity=20)
states, infos = mt.run(cphd, sample.zs)
print(infos.extra["cardinality"][-1], infos.extra["cardinality_variance"][-1])
print(infos.extra["n_estimates"], sample.alive.sum(-1))
"""


def test_docs_snippet_runs():
    blocks = re.findall(r"^```python\n(.*?)^```", DOCS_PAGE.read_text(), flags=re.S | re.M)
    assert DOCS_SNIPPET in blocks
    namespace: dict = {}
    exec(compile(DOCS_SNIPPET, str(DOCS_PAGE), "exec"), namespace)
    infos, sample = namespace["infos"], namespace["sample"]
    assert infos.extra["cardinality_variance"].shape == (20,)
    assert np.mean(np.asarray(infos.extra["n_estimates"]) == np.asarray(sample.alive).sum(-1)) > 0.8


# ----------------------------------------------------------------------------- PHD vs CPHD cardinality


def _jackknife_se(stat, n_runs):
    vals = np.array([stat(np.arange(n_runs) != i) for i in range(n_runs)])
    return float(np.sqrt((n_runs - 1) / n_runs * np.sum((vals - vals.mean()) ** 2)))


def cardinality_variance_stats(estimates, truth):
    """Across-run variance of cardinality estimates, with jackknife (over runs) standard errors.

    Args:
        estimates: name -> ``(N, T)`` cardinality estimates of ``N`` runs. The scenarios' tracks are
            deterministic, so at a step every run has the same true cardinality and the variance across
            runs is the estimator's.
        truth: ``(N, T)`` true cardinalities.

    Returns:
        name -> ``var`` (the per-step variance across runs, ``ddof = 1``, averaged over the steps),
        ``mse`` (against the truth) and their standard errors, and for the pairs ``cphd_mean - phd_mass``
        and ``cphd_map - phd_count`` the paired difference of ``var`` with its standard error.
    """
    est = {k: np.asarray(v, np.float64) for k, v in estimates.items()}
    truth = np.asarray(truth, np.float64)
    n_runs = truth.shape[0]
    everyone = np.ones(n_runs, bool)

    def var(x):
        return lambda sel: float(np.mean(np.var(x[sel], axis=0, ddof=1)))

    def mse(x):
        return lambda sel: float(np.mean((x[sel] - truth[sel]) ** 2))

    out: dict = {}
    for name, x in est.items():
        out[name] = {
            "var": var(x)(everyone),
            "var_se": _jackknife_se(var(x), n_runs),
            "mse": mse(x)(everyone),
            "mse_se": _jackknife_se(mse(x), n_runs),
        }
    for a, b in (("cphd_mean", "phd_mass"), ("cphd_map", "phd_count")):

        def diff(sel, a=a, b=b):
            return var(est[a])(sel) - var(est[b])(sel)

        out[f"{a}-{b}"] = {"var": diff(everyone), "var_se": _jackknife_se(diff, n_runs)}
    return out


def _estimates(phd_infos, cphd_infos, start):
    """The four estimators, steps ``start ..``: the PHD's mass (``sum w``, Vo & Ma eq 29's ``N_k``) and
    Table III count; the CPHD's mean and MAP cardinality (the number it extracts)."""
    est = {
        "phd_mass": phd_infos.extra["cardinality"],
        "phd_count": phd_infos.extra["n_estimates"],
        "cphd_mean": cphd_infos.extra["cardinality"],
        "cphd_map": cphd_infos.extra["n_estimates"],
    }
    return {k: np.asarray(v)[:, start:] for k, v in est.items()}


def _print_study(out, header):
    print(f"\n{header}")
    for name, r in out.items():
        extra = f"  MSE {r['mse']:.4f} +- {r['mse_se']:.4f}" if "mse" in r else ""
        print(f"{name:>20}: var {r['var']:.4f} +- {r['var_se']:.4f}{extra}")


def test_cardinality_variance_study_small(small, small_filter):
    """The study's statistics on 6 short runs of the small scenario (shared CPHD program): finite numbers,
    no flags; no direction asserted."""
    sc, _ = small
    f, run = small_filter
    samples = jax.vmap(lambda k: mt.simulate(sc, k))(jax.random.split(jax.random.PRNGKey(5), 6))
    merge = (CAP + 2) * (1 + sc.max_measurements)
    phd_f = mt.gm_phd(sc.model, **sc.filter_kwargs(), capacity=CAP, merge_capacity=merge)
    run_phd = jax.jit(lambda z: mt.run(phd_f, z))
    outs_c = [run(z, f.params, f.init(f.params))[1] for z in samples.zs]
    outs_p = [run_phd(z)[1] for z in samples.zs]
    stack = lambda infos: jax.tree_util.tree_map(lambda *a: np.stack(a), *infos)  # noqa: E731
    ic, ip = stack(outs_c), stack(outs_p)
    assert not np.any(ic.flags.any()) and not np.any(ip.flags.any())
    out = cardinality_variance_stats(_estimates(ip, ic, 2), np.asarray(samples.alive).sum(-1)[:, 2:])
    _print_study(out, "6 runs x 8 steps (steps 3..8)")
    for r in out.values():
        assert np.isfinite(r["var"]) and np.isfinite(r["var_se"])


@pytest.mark.slow
def test_cardinality_variance_phd_vs_cphd():
    """64 runs x 100 steps of Vo & Ma's scenario (clutter 10 per scan, P_D = 0.98), both filters on the
    same measurements (capacity 30, Vo-Ma T = 1e-5, U = 4; N_max = 30), steps 6..100.

    Measured (seed 2007, x64): variance of the cardinality estimate across runs, averaged over the steps,
    +- a jackknife standard error over runs:

    ===========  ================  ===============
    estimator    variance          MSE vs truth
    ===========  ================  ===============
    PHD mass     0.1380 +- 0.0058  0.1404 +- 0.0058
    PHD count    0.1622 +- 0.0067  0.1630 +- 0.0066
    CPHD mean    0.0612 +- 0.0033  0.0783 +- 0.0040
    CPHD MAP     0.0841 +- 0.0047  0.1049 +- 0.0055
    ===========  ================  ===============

    Paired differences (CPHD - PHD): mean vs mass -0.0769 +- 0.0035, MAP vs count -0.0781 +- 0.0047,
    i.e. more than 3 standard errors, so the direction is asserted (on these runs).
    """
    sc = mt.vo_ma_linear(n_steps=100, max_measurements=32)
    n_runs = 64
    samples = jax.jit(jax.vmap(lambda k: mt.simulate(sc, k)))(
        jax.random.split(jax.random.PRNGKey(2007), n_runs)
    )
    kw = dict(capacity=30, merge_capacity=120)
    phd_f = mt.gm_phd(sc.model, **sc.filter_kwargs(), **kw)
    cphd_f = mt.gm_cphd(sc.model, **sc.filter_kwargs(), n_max=30, **kw)
    _, ip = jax.jit(jax.vmap(lambda z: mt.run(phd_f, z)))(samples.zs)
    _, ic = jax.jit(jax.vmap(lambda z: mt.run(cphd_f, z)))(samples.zs)
    assert not np.any(samples.overflow)
    assert not np.any(ic.flags.any()) and not np.any(ip.flags.any())
    out = cardinality_variance_stats(_estimates(ip, ic, 5), np.asarray(samples.alive).sum(-1)[:, 5:])
    _print_study(out, f"{n_runs} runs x 100 steps (steps 6..100)")
    for pair in ("cphd_mean-phd_mass", "cphd_map-phd_count"):
        assert out[pair]["var_se"] > 0 and out[pair]["var"] < -3 * out[pair]["var_se"]
