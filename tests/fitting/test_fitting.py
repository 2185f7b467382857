"""gmjax.fit / gmjax.fitting (issue 45): learning a filter's parameters by maximum likelihood or a study loss.

Independent references: the exact Kalman likelihood and its scipy ML optimum
(references/kalman_np.py), the point-mass grid likelihood and its ML mixture
(references/gm_noise_np.py), and central differences of every objective.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import gmjax
from gmjax import GaussianMixture, filters, fitting, reduction
from gmjax import multitarget as mt
from gmjax.models import StateSpaceModel
from gmjax.montecarlo import armse_loss
from gmjax.scenarios.jump_system import jump_system
from references import gm_noise_np, kalman_np  # the repository root is on sys.path (conftest)

# the scalar model of gm_noise_np with a 2-component measurement noise whose components are separated by
# about 4 innovation standard deviations. (With the overlapping truth of test_reference_gm_noise.py,
# q = 0.5, means -1.5/0.8, variances 0.4/1.2, the GSF fits equal the grid ML, but the ML estimator is
# itself biased at T = 300: 2.4-3.7 standard errors over 20 data sets, seeds 100..119.)
A, Q, M0, P0 = 0.9, 0.1, 0.0, 2.0
W_TRUE, MU_TRUE, S2_TRUE = np.array([0.3, 0.7]), np.array([-2.0, 1.0]), np.array([0.3, 0.6])
NOISE = "model.measurement_noise"


def _simulate_gm(rng, T):
    x, xs = M0 + np.sqrt(P0) * rng.normal(), []
    for _ in range(T):
        x = A * x + np.sqrt(Q) * rng.normal()
        xs.append(x)
    j = rng.choice(2, size=T, p=W_TRUE)
    return np.array(xs) + MU_TRUE[j] + np.sqrt(S2_TRUE[j]) * rng.normal(size=T)


def _gm_model(weights, means, variances):
    return StateSpaceModel(
        f=lambda x, t: A * x,
        h=lambda x, t: x,
        process_noise=GaussianMixture.create([1.0], [[0.0]], [[[Q]]]),
        measurement_noise=GaussianMixture.create(
            weights, np.asarray(means)[:, None], np.asarray(variances)[:, None, None]
        ),
        prior=GaussianMixture.create([1.0], [[M0]], [[[P0]]]),
    )


@pytest.fixture(scope="module")
def gm_gsf():
    """A linear GSF with a 2-component measurement noise started at (0.5, 0.5), (-1, 1), (1, 1).
    Runnalls merging keeps its likelihood within ~1e-3 nat of the exact one over 300 steps (pruning to
    the 6 heaviest components: 0.3-1.1 nat off)."""
    return filters.build_gsf(
        _gm_model([0.5, 0.5], [-1.0, 1.0], [1.0, 1.0]), "kf", reduction.Runnalls(num_out=6), capacity=6
    )


def _gm_values(res_values):
    w = res_values[NOISE + ".weights"]
    mu = res_values[NOISE + ".means"][:, 0]
    s2 = res_values[NOISE + ".covs"][:, 0, 0]
    order = np.argsort(mu)
    return w[order], mu[order], s2[order]


def _central(f, u, h):
    """Central differences of ``f`` at the dict ``u`` of arrays, entry by entry (same structure)."""
    out = {}
    for n, x in u.items():
        x = np.asarray(x, np.float64)
        g = np.zeros_like(x)
        for i in np.ndindex(x.shape):
            e = np.zeros_like(x)
            e[i] = h
            g[i] = (float(f({**u, n: jnp.asarray(x + e)})) - float(f({**u, n: jnp.asarray(x - e)}))) / (2 * h)
        out[n] = g
    return out


def _check_gradient(filter, data, objective, names, *, h, rtol, atol=0.0, constraints=None, key=None):
    view = fitting.param_view(filter.params, names, constraints)
    loss = fitting.loss_fn(filter, data, objective, view)
    key = jax.random.key(3) if key is None else key
    u = view.unconstrained()
    value, grad = jax.jit(jax.value_and_grad(loss))(u, key)
    f = jax.jit(loss)
    fd = _central(lambda v: f(v, key), u, h)
    assert np.isfinite(float(value))
    for n in view.names:
        g = np.asarray(grad[n])
        assert np.all(np.isfinite(g)) and np.any(g != 0), n
        np.testing.assert_allclose(g, fd[n], rtol=rtol, atol=atol, err_msg=n)
    return value, grad


# ----------------------------------------------------------------------------- Kalman filter: exact optimum


def test_kf_noise_variances_equal_the_exact_ml_optimum():
    F, H, m0, P0_ = np.array([[0.95]]), np.array([[1.0]]), np.zeros(1), 4.0 * np.eye(1)
    rng = np.random.default_rng(0)
    zs = np.empty((3, 80, 1))
    for b in range(3):
        x = rng.normal(0, 2, 1)
        for t in range(80):
            x = F @ x + rng.normal(0, np.sqrt(0.3), 1)
            zs[b, t] = H @ x + rng.normal(0, np.sqrt(1.5), 1)
    q, r, _ = kalman_np.ml_noise_variances(zs, F, H, m0, P0_, 1.0, 1.0, np.eye(1), np.eye(1))
    kf = filters.kalman_filter(F, H, np.eye(1), np.eye(1), m0, P0_)
    res = gmjax.fit(kf, zs, fit=["Q", "R"], key=jax.random.key(0), progress=False)
    assert res.converged and res.n_skipped == 0
    np.testing.assert_allclose([res.values["Q"][0, 0], res.values["R"][0, 0]], [q, r], rtol=1e-6)
    # the loss is the exact negative log-likelihood per step at the fitted values
    exact = (
        -kalman_np.kalman_loglik_batch(zs, F, H, res.values["Q"], res.values["R"], m0, P0_) / zs[..., 0].size
    )
    np.testing.assert_allclose(res.history.loss[-1], exact, rtol=1e-10)
    # gradient of the objective against central differences (unconstrained softplus coordinates)
    _check_gradient(kf, zs, fitting.nll(), ["Q", "R"], h=1e-5, rtol=1e-6)


def test_kf_fit_in_float32_lands_near_the_float64_optimum():
    F, H = np.array([[0.9]]), np.array([[1.0]])
    rng = np.random.default_rng(1)
    zs = rng.normal(size=(60, 1)).cumsum(0) * 0.3 + rng.normal(size=(60, 1))
    kf64 = filters.kalman_filter(F, H, np.eye(1), np.eye(1), np.zeros(1), np.eye(1))
    kf32 = filters.kalman_filter(
        *(np.asarray(a, np.float32) for a in (F, H, np.eye(1), np.eye(1), np.zeros(1), np.eye(1)))
    )
    r64 = gmjax.fit(kf64, zs, fit="R", key=jax.random.key(0), progress=False)
    r32 = gmjax.fit(kf32, zs.astype(np.float32), fit="R", key=jax.random.key(0), progress=False, ftol=1e-7)
    assert r32.values["R"].dtype == np.float32
    np.testing.assert_allclose(r32.values["R"], r64.values["R"], rtol=1e-3)


# ----------------------------------------------------------------------------- GSF: Gaussian-mixture noise


def test_gsf_likelihood_equals_the_grid_likelihood_and_its_gradient_central_differences(gm_gsf):
    zs = _simulate_gm(np.random.default_rng(11), 150)
    view = fitting.param_view(gm_gsf.params, NOISE)
    loss = jax.jit(fitting.loss_fn(gm_gsf, zs[:, None], fitting.nll(), view))
    L = 14 * np.sqrt(Q / (1 - A * A))
    grid = np.linspace(-L, L, 201)
    for w, mu, s2 in [
        ((0.5, 0.5), (-1.0, 1.0), (1.0, 1.0)),
        (W_TRUE, MU_TRUE, S2_TRUE),
        ((0.1, 0.9), (-3.0, 0.2), (0.2, 2.0)),
    ]:
        p = gm_gsf.params._replace(
            model=gm_gsf.params.model._replace(measurement_noise=_gm_model(w, mu, s2).measurement_noise)
        )
        got = float(loss(view.unconstrained(p), jax.random.key(0)))
        ref = -gm_noise_np.grid_loglik(zs, A, Q, w, mu, s2, M0, P0, grid) / zs.size
        assert abs(got - ref) < 2e-3 / zs.size * 150, (w, got, ref)  # the reduction's approximation
    _check_gradient(gm_gsf, zs[:, None], fitting.nll(), [NOISE], h=1e-5, rtol=1e-5, atol=1e-9)


@pytest.mark.slow
def test_gsf_ml_mixture_equals_the_grid_ml_mixture(gm_gsf):
    zs = _simulate_gm(np.random.default_rng(0), 300)
    res = gmjax.fit(gm_gsf, zs[:, None], fit=NOISE, key=jax.random.key(0), progress=False, steps=300)
    assert res.converged
    L = 14 * np.sqrt(Q / (1 - A * A))
    ref = gm_noise_np.ml_fit_grid(zs, A, Q, M0, P0, np.linspace(-L, L, 201), [0.5, 0.5], [-1, 1], [1, 1])
    w, mu, s2 = _gm_values(res.values)
    # the GSF's likelihood is the exact one to ~1e-3 nat (Runnalls), so the optima agree to ~1e-4
    np.testing.assert_allclose(w, ref["weights"], atol=1e-3)
    np.testing.assert_allclose(mu, ref["means"], atol=1e-3)
    np.testing.assert_allclose(s2, ref["variances"], rtol=2e-3)
    assert abs(res.loss + ref["loglik"] / zs.size) < 1e-5


@pytest.mark.slow
def test_gsf_ml_recovers_the_true_mixture_over_20_data_sets(gm_gsf):
    """Each parameter's mean over 20 independent data sets (T = 300) lies within 3 standard errors of
    the truth (components ordered by mean)."""
    est = []
    for s in range(20):
        zs = _simulate_gm(np.random.default_rng(100 + s), 300)
        res = gmjax.fit(gm_gsf, zs[:, None], fit=NOISE, key=jax.random.key(0), progress=False, steps=300)
        assert res.converged, s
        est.append(np.concatenate(_gm_values(res.values)))
    est = np.asarray(est)
    truth = np.concatenate([W_TRUE, MU_TRUE, S2_TRUE])
    mean, se = est.mean(0), est.std(0, ddof=1) / np.sqrt(len(est))
    z = (mean - truth) / se
    assert np.all(np.abs(z) < 3.0), dict(mean=mean, se=se, z=z)


@pytest.mark.slow
def test_misspecified_kalman_filter_cannot_learn_the_mixture(gm_gsf):
    """Negative control: a Kalman filter (one Gaussian) fitted to the same mixture-noise data learns the
    mixture's overall variance, matches neither component, and explains the data worse than the GSF."""
    zs = _simulate_gm(np.random.default_rng(5), 300)[:, None]
    kf = filters.kalman_filter([[A]], [[1.0]], [[Q]], [[1.0]], [M0], [[P0]])
    res_kf = gmjax.fit(kf, zs, fit="R", key=jax.random.key(0), progress=False)
    res_gsf = gmjax.fit(gm_gsf, zs, fit=NOISE, key=jax.random.key(0), progress=False, steps=300)
    assert res_kf.converged and res_gsf.converged
    r = float(res_kf.values["R"][0, 0])
    total = float(W_TRUE @ S2_TRUE + W_TRUE @ MU_TRUE**2 - (W_TRUE @ MU_TRUE) ** 2)
    assert abs(r - total) < 0.3 * total and np.all(np.abs(r - S2_TRUE) > 0.5)
    # the GSF nests the KF (one Gaussian is a mixture), so its optimum is at least as good
    assert res_gsf.loss <= res_kf.loss
    # KL(true noise || learned noise) by dense quadrature: the KF's Gaussian is the far worse density
    x = np.linspace(-12.0, 12.0, 24001)
    true = np.exp(gm_noise_np.gm_logpdf(x, W_TRUE, MU_TRUE, S2_TRUE))

    def kl(logq):
        return float(np.sum(true * (np.log(true) - logq)) * (x[1] - x[0]))

    kl_kf = kl(gm_noise_np.gm_logpdf(x, [1.0], [0.0], [r]))
    kl_gsf = kl(gm_noise_np.gm_logpdf(x, *_gm_values(res_gsf.values)))
    assert kl_kf > 2 * kl_gsf, (kl_kf, kl_gsf)


def test_imm_transition_matrix_by_likelihood_stays_stochastic_and_its_gradient_matches():
    """An IMM of a quiet and a noisy measurement regime: the transition matrix is fitted on the simplex of
    each row (the default for ``transition``), its likelihood gradient against central differences."""
    rng = np.random.default_rng(4)
    P_true = np.array([[0.95, 0.05], [0.1, 0.9]])
    r = np.array([0.2, 4.0])
    x, mode, zs = 0.0, 0, []
    for _ in range(120):
        mode = rng.choice(2, p=P_true[mode])
        x = 0.9 * x + rng.normal(0.0, np.sqrt(0.3))
        zs.append([x + rng.normal(0.0, np.sqrt(r[mode]))])
    models = [
        StateSpaceModel(
            f=lambda x, t: 0.9 * x,
            h=lambda x, t: x,
            process_noise=GaussianMixture.create([1.0], [[0.0]], [[[0.3]]]),
            measurement_noise=GaussianMixture.create([1.0], [[0.0]], [[[ri]]]),
            prior=GaussianMixture.create([1.0], [[0.0]], [[[1.0]]]),
        )
        for ri in r
    ]
    imm = filters.build_imm(models, [[0.7, 0.3], [0.3, 0.7]], filter="kf")
    zs = np.asarray(zs)
    view = fitting.param_view(imm.params, "transition")
    assert view.constraints == {"transition": "stochastic"}
    _check_gradient(imm, zs, fitting.nll(), ["transition"], h=1e-5, rtol=1e-5, atol=1e-10)
    res = gmjax.fit(imm, zs, fit="transition", key=jax.random.key(0), progress=False)
    P = res.values["transition"]
    np.testing.assert_allclose(P.sum(1), 1.0, rtol=1e-12)
    assert res.converged and res.history.loss[-1] < res.history.loss[0]
    assert P[0, 0] > 0.7 and P[1, 1] > 0.7  # both regimes persist (truth 0.95, 0.9)


# ----------------------------------------------------------------------------- study losses


@pytest.fixture(scope="module")
def short_jump():
    return jump_system(n_steps=12)


def test_reducer_threshold_study_gradient_matches_central_differences(short_jump):
    red = reduction.PruneThreshold(threshold=0.2, mode="soft", temperature=0.1)
    gsf = filters.build_gsf(short_jump.model, "ekf", red, capacity=8)
    _check_gradient(
        gsf,
        short_jump,
        fitting.study(armse_loss(), n_runs=6),
        ["reducer.threshold"],
        h=1e-5,
        rtol=1e-5,
        constraints={"reducer.threshold": (1e-4, 0.9)},
    )


def test_pf_jitter_study_gradient_matches_central_differences(short_jump):
    """The regularised PF's bandwidth scale: pathwise derivative with the resampling indices held (common
    random numbers); central differences with a small step cross no index change."""
    pf = filters.build_pf(short_jump.model, 64, regularized=True, bandwidth_scale=0.5)
    _check_gradient(
        pf, short_jump, fitting.study(armse_loss(), n_runs=4), ["bandwidth_scale"], h=1e-6, rtol=1e-4
    )


@pytest.mark.slow
def test_pf_jitter_fits_through_the_study_loss(short_jump):
    """A few Adam steps on the regularised PF's bandwidth scale: every step finite, the bandwidth moves."""
    pf = filters.build_pf(short_jump.model, 64, regularized=True, bandwidth_scale=0.5)
    objective = fitting.study(armse_loss(), n_runs=4)
    res = gmjax.fit(
        pf,
        short_jump,
        objective,
        fit="bandwidth_scale",
        key=jax.random.key(3),
        optimizer=optax.adam(0.2),
        steps=4,
        progress=False,
    )
    assert res.n_steps == 4 and res.n_skipped == 0 and np.all(np.isfinite(res.history.loss))
    assert res.values["bandwidth_scale"] != pytest.approx(0.5)


@pytest.fixture(scope="module")
def small_phd():
    sc = mt.vo_ma_linear(n_steps=5, max_measurements=16, clutter_rate=5.0)
    phd = mt.gm_phd(
        sc.model,
        **sc.filter_kwargs(),
        capacity=10,
        merge_capacity=40,
        reducer=mt.RelaxedVoMa(1e-3, 4.0, 5e-4, 1.0, max_components=10),
    )
    return sc, phd


def test_phd_clutter_and_birth_study_gradient_matches_central_differences(small_phd):
    sc, phd = small_phd
    _check_gradient(
        phd,
        sc,
        fitting.study(mt.gospa_loss(c=50.0), n_runs=2),
        ["clutter_rate", "birth.weights"],
        h=1e-5,
        rtol=1e-4,
    )


@pytest.mark.slow
def test_phd_likelihood_gradient_matches_central_differences(small_phd):
    sc, phd = small_phd
    samples = jax.vmap(lambda k: mt.simulate(sc, k))(jax.random.split(jax.random.key(2), 2))
    _check_gradient(phd, samples.zs, fitting.nll(), ["clutter_rate", "birth.weights"], h=1e-5, rtol=1e-5)


@pytest.mark.slow
def test_phd_fit_by_study_loss_runs_and_lowers_the_loss(small_phd):
    sc, phd = small_phd
    start = phd.params._replace(clutter_rate=jnp.asarray(40.0))  # far too much clutter assumed
    res = gmjax.fit(
        phd,
        sc,
        fitting.study(mt.gospa_loss(c=50.0), n_runs=2),
        fit="clutter_rate",
        params=start,
        key=jax.random.key(1),
        steps=8,
        progress=False,
    )
    assert res.n_skipped == 0 and res.history.loss[-1] < res.history.loss[0]
    assert res.values["clutter_rate"] < 40.0


@pytest.mark.slow
def test_fitted_prune_threshold_beats_the_default_on_held_out_runs():
    """jump_system (40 steps), GSF with weight-threshold pruning: the default 0.4 prunes too much; the
    threshold fitted on the soft study loss (training key 1) lowers the hard filter's held-out ARMSE
    (400 paired runs, key 2026) by more than the paired difference's standard error."""
    sc = jump_system(n_steps=40)
    soft = reduction.PruneThreshold(threshold=0.4, mode="soft", temperature=0.1)
    gsf = filters.build_gsf(sc.model, "ekf", soft, capacity=16)
    res = gmjax.fit(
        gsf,
        sc,
        fitting.study(armse_loss(), n_runs=32),
        fit="reducer.threshold",
        constraints={"reducer.threshold": (1e-4, 0.9)},
        key=jax.random.key(1),
        steps=30,
        progress=False,
    )
    thr = float(res.values["reducer.threshold"])
    assert thr < 0.4

    def held_out(threshold):
        f = filters.build_gsf(sc.model, "ekf", reduction.PruneThreshold(threshold=threshold), capacity=16)
        return np.asarray(gmjax.montecarlo.study_scores(f, sc, 400, jax.random.key(2026)).position_sq_error)

    a, b = held_out(0.4), held_out(thr)
    # per-run mean squared errors, paired; the ARMSE difference's delta-method standard error
    ra, rb = np.sqrt(a.mean(0)), np.sqrt(b.mean(0))
    da = (a - a.mean(0)) / (2 * ra) / a.shape[0]
    db = (b - b.mean(0)) / (2 * rb) / b.shape[0]
    contrib = (da - db).mean(1)  # each run's contribution to mean_t(rmse_a - rmse_b)
    diff = float(np.mean(ra - rb))
    se = float(np.sqrt(np.sum(contrib**2) * a.shape[0] / (a.shape[0] - 1)))
    assert diff > se, (thr, diff, se)


# ----------------------------------------------------------------------------- the loop: resume, errors


def _small_kf():
    rng = np.random.default_rng(0)
    zs = rng.normal(size=(2, 50, 1)).cumsum(1)
    return filters.kalman_filter([[0.95]], [[1.0]], [[1.0]], [[1.0]], [0.0], [[4.0]]), zs


def test_a_resumed_fit_continues_bit_for_bit(tmp_path):
    kf, zs = _small_kf()
    kw = dict(fit=["Q", "R"], key=jax.random.key(0), progress=False, gtol=0.0, ftol=0.0)
    whole = gmjax.fit(kf, zs, steps=10, **kw)
    path = tmp_path / "fit.npz"
    part = gmjax.fit(kf, zs, steps=4, checkpoint=path, **kw)  # "killed" after 4 steps
    assert part.n_steps == 4 and path.exists()
    resumed = gmjax.fit(kf, zs, steps=10, checkpoint=path, **kw)
    assert resumed.n_steps == 10
    np.testing.assert_array_equal(resumed.history.loss, whole.history.loss)
    for n in ("Q", "R"):
        np.testing.assert_array_equal(resumed.values[n], whole.values[n])
        np.testing.assert_array_equal(resumed.history.values[n], whole.history.values[n])
    assert not list(tmp_path.glob("*.tmp-*"))
    # another fit's checkpoint is refused naming what differs; resume=False starts again
    with pytest.raises(ValueError, match=r"written by another fit \(differs in: data\)"):
        gmjax.fit(kf, zs[:, :40], steps=10, checkpoint=path, **kw)
    with pytest.raises(ValueError, match=r"differs in: constraints, fit, optimizer_state\)"):
        gmjax.fit(kf, zs, steps=10, checkpoint=path, **{**kw, "fit": "R"})
    again = gmjax.fit(kf, zs, steps=3, checkpoint=path, resume=False, **kw)
    np.testing.assert_array_equal(again.history.loss, whole.history.loss[:3])
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(ValueError, match="truncated or corrupt.*resume=False"):
        gmjax.fit(kf, zs, steps=10, checkpoint=path, **kw)


def test_fit_is_a_top_level_name_and_the_jit_step_equals_the_eager_loss():
    assert gmjax.fit is fitting.fit
    kf, zs = _small_kf()
    view = fitting.param_view(kf.params, ["Q", "R"])
    loss = fitting.loss_fn(kf, zs, fitting.nll(), view)
    u, k = view.unconstrained(), jax.random.key(0)
    np.testing.assert_allclose(float(loss(u, k)), float(jax.jit(loss)(u, k)), rtol=1e-12)
    res = gmjax.fit(kf, zs, fit=["Q", "R"], key=k, progress=False, steps=1)
    assert res.history.loss[0] == pytest.approx(float(loss(u, k)), rel=1e-12)


def test_bad_arguments_are_refused_naming_them(small_phd, short_jump):
    kf, zs = _small_kf()
    kw = dict(key=jax.random.key(0), progress=False)
    with pytest.raises(ValueError, match=r"^fit: 'model.Q' names no floating leaf .* the leaves are \['F'"):
        gmjax.fit(kf, np.zeros((5, 1)), fit="model.Q", **kw)
    with pytest.raises(ValueError, match=r"fit: 'Q' starts at .* must be symmetric positive definite"):
        gmjax.fit(kf, zs, fit="Q", params=kf.params._replace(Q=-jnp.eye(1)), constraints={"Q": "spd"}, **kw)
    with pytest.raises(ValueError, match=r"constraints\['R'\]: need low < high"):
        gmjax.fit(kf, zs, fit="R", constraints={"R": (2.0, 1.0)}, **kw)
    with pytest.raises(ValueError, match=r"^data: expected float measurements"):
        gmjax.fit(kf, np.zeros(5), fit="R", **kw)
    with pytest.raises(ValueError, match=r"^steps: must be a positive int"):
        gmjax.fit(kf, zs, fit="R", steps=0, **kw)
    with pytest.raises(ValueError, match=r"^key: expected a PRNG key"):
        gmjax.fit(kf, zs, fit="R", key=0, progress=False)
    with pytest.raises(ValueError, match=r"^data: the study objective needs a Scenario"):
        gmjax.fit(kf, zs, fitting.study(), fit="R", **kw)
    sc, phd = small_phd
    with pytest.raises(ValueError, match=r"^data: a MultiTargetScenario goes with a GM-PHD filter"):
        gmjax.fit(kf, sc, fit="R", **kw)
    with pytest.raises(ValueError, match=r"^data: a MultiTargetScenario goes with a GM-PHD filter"):
        gmjax.fit(phd, short_jump, fit="clutter_rate", **kw)
    with pytest.raises(ValueError, match=r"^c: must be a positive number"):
        mt.gospa_loss(c=0.0)
    with pytest.raises(ValueError, match=r"^checkpoint_every"):
        gmjax.fit(kf, zs, fit="R", checkpoint_every=-1, **kw)
    assert not os.path.exists("fit.npz")


# the GM-LMB case is slow (about 35 s); its clutter-rate gradient is checked against central
# differences in the default suite (test_lmb)
@pytest.mark.parametrize("which", ["cphd", pytest.param("lmb", marks=pytest.mark.slow)])
def test_clutter_rate_by_maximum_likelihood_is_the_grid_optimum_near_the_truth(which):
    """``gmjax.fit`` with ``nll()`` on padded sets for the GM-CPHD (its exact i.i.d.-cluster likelihood)
    and the GM-LMB (the likelihood of its drawn hypotheses, the same draws every step): the fitted
    clutter rate is the minimiser of the same objective on a grid, and near the simulated rate."""
    sc = mt.vo_ma_linear(n_steps=12, max_measurements=32, clutter_rate=10.0)
    zs = jax.vmap(lambda k: mt.simulate(sc, k).zs)(jax.random.split(jax.random.key(5), 4))
    if which == "cphd":
        f = mt.gm_cphd(sc.model, **sc.filter_kwargs(), n_max=12, capacity=12)
    else:
        f = mt.gm_lmb(sc.model, **sc.filter_kwargs(), capacity=10, components_per_track=3, n_samples=60)
    start = f.params._replace(clutter_rate=jnp.asarray(4.0))
    key = jax.random.key(2)
    res = gmjax.fit(f, zs, fitting.nll(), fit="clutter_rate", params=start, key=key, steps=40, progress=False)
    assert res.converged and res.n_skipped == 0
    view = fitting.param_view(start, ["clutter_rate"])
    loss = jax.jit(fitting.loss_fn(f, zs, fitting.nll(), view))
    grid = np.linspace(7.0, 13.0, 31)
    at = lambda g: view.unconstrained(start._replace(clutter_rate=jnp.asarray(g)))  # noqa: E731
    values = [float(loss(at(g), key)) for g in grid]
    best = grid[int(np.argmin(values))]
    assert abs(res.values["clutter_rate"] - best) <= grid[1] - grid[0]
    assert abs(res.values["clutter_rate"] - 10.0) < 2.0
