"""Linear GSF bank with the seed 004 reductions (gmjax.filters.bank)."""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import filters
from gmjax import mixture as gmm
from gmjax.filters import StepInputs, bank
from gmjax.models import ModelParams
from gmjax.scenarios import uwb_velocity

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from references.bank_np import _dare, bank_filter_np  # noqa: E402

DT = uwb_velocity.DT
F = np.array([[1.0, DT], [0.0, 1.0]])
H = np.array([[1.0, 0.0]])
G = np.array([[DT], [1.0]])
PRIOR = (np.zeros(2), 100.0 * np.eye(2))
T = 25  # one horizon everywhere, so each method's kernel compiles once for the whole file


def _model(process, measurement, dtype=jnp.float64):
    return uwb_velocity.rwv_model(process, measurement, dtype=dtype)


def _inputs(active):
    """Times ``1..T`` and the true active pairs ``(T, 2)`` (read by ``matched``) as ``inputs.aux``."""
    return StepInputs(t=jnp.arange(1, active.shape[0] + 1, dtype=jnp.int32), aux=active)


def _params(filt, q, r):
    """``filt.params`` with the noise mixtures replaced (a traced pytree: one kernel per shape)."""
    return bank.BankParams(ModelParams(filt.params.model.prior, q, r))


@functools.cache
def _runner(method: str, dtype=jnp.float64):
    """One compiled kernel per (method, shapes): the noise mixtures are traced arguments of params."""
    base = _model(uwb_velocity.synthetic_noise(1, 1.0), uwb_velocity.synthetic_noise(1, 1.0), dtype)
    filt = bank.build_bank(base, method, noise_gain=jnp.asarray(G, dtype))

    @jax.jit
    def run(q, r, zs, active):
        return filters.run(filt, zs, _inputs(active), params=_params(filt, q, r))

    return run


def _np_noise(gm):
    mask = np.asarray(gm.mask)
    return tuple(np.asarray(a, float)[mask] for a in (gm.weights, gm.means, gm.covs))


def _simulate(process, measurement, seed, n_steps):
    return uwb_velocity.simulate_labeled(process, measurement, jax.random.key(seed), n_steps=n_steps)


def test_each_method_matches_the_numpy_reference_on_model_3():
    noise = uwb_velocity.synthetic_noise(3, 0.6)
    model = _model(noise, noise)
    run = _simulate(noise, noise, 1, T)
    q, r = model.process_noise, model.measurement_noise
    for method in bank.BANK_METHODS:
        _, infos = _runner(method)(q, r, run.zs, run.active)
        ref = bank_filter_np(
            method,
            np.asarray(run.zs),
            F,
            H,
            _np_noise(q),
            _np_noise(r),
            PRIOR,
            active=np.asarray(run.active),
            G=G,
        )
        np.testing.assert_allclose(np.asarray(infos.mean), ref, rtol=1e-9, atol=1e-9, err_msg=method)
        assert not bool(infos.flags.repaired.any() | infos.flags.degenerate.any()), method


@pytest.mark.slow
@pytest.mark.parametrize("axis", ["x", "y"])
def test_each_method_matches_the_numpy_reference_on_uwb(axis):
    pn, mn = uwb_velocity.UWB_NOISES[axis]["process"], uwb_velocity.UWB_NOISES[axis]["measurement"]
    model = _model(pn, mn)
    run = _simulate(pn, mn, 2, 40)
    q, r = model.process_noise, model.measurement_noise
    for method in bank.BANK_METHODS:
        filt = bank.build_bank(model, method)  # noise_gain="auto" here
        _, infos = jax.jit(lambda zs, a: filters.run(filt, zs, _inputs(a)))(run.zs, run.active)
        ref = bank_filter_np(
            method,
            np.asarray(run.zs),
            F,
            H,
            _np_noise(q),
            _np_noise(r),
            PRIOR,
            active=np.asarray(run.active),
            G=G,
        )
        np.testing.assert_allclose(np.asarray(infos.mean), ref, rtol=1e-9, atol=1e-7, err_msg=method)


def _one_component_check(q, r, zs, active, runner_for):
    model = _model(
        uwb_velocity.ScalarGM((1.0,), (2.0,), (1.5,)), uwb_velocity.ScalarGM((1.0,), (-1.0,), (4.0,))
    )
    kf_states, _ = jax.jit(lambda z: filters.run(filters.build_kf(model), z))(zs)
    for method in bank.BANK_METHODS:
        _, infos = runner_for(method)(q, r, zs, active)
        np.testing.assert_allclose(
            np.asarray(infos.mean), np.asarray(kf_states.mean), rtol=1e-10, atol=1e-10, err_msg=method
        )
        np.testing.assert_allclose(
            np.asarray(infos.cov), np.asarray(kf_states.cov), rtol=1e-10, atol=1e-10, err_msg=method
        )


def test_one_component_noises_every_method_equals_the_kalman_filter():
    """One live cluster per noise, stored in 5 padded slots (the shapes of Table I)."""
    pn, mn = uwb_velocity.ScalarGM((1.0,), (2.0,), (1.5,)), uwb_velocity.ScalarGM((1.0,), (-1.0,), (4.0,))
    model = _model(pn, mn)
    q, r = gmm.pad(model.process_noise, 5), gmm.pad(model.measurement_noise, 5)
    run = _simulate(pn, mn, 3, T)
    _one_component_check(q, r, run.zs, jnp.zeros((T, 2), jnp.int32), _runner)


@pytest.mark.slow
def test_one_component_noises_unpadded_every_method_equals_the_kalman_filter():
    pn, mn = uwb_velocity.ScalarGM((1.0,), (2.0,), (1.5,)), uwb_velocity.ScalarGM((1.0,), (-1.0,), (4.0,))
    model = _model(pn, mn)
    run = _simulate(pn, mn, 4, 30)
    _one_component_check(
        model.process_noise,
        model.measurement_noise,
        run.zs,
        jnp.zeros((30, 2), jnp.int32),
        functools.partial(_runner),
    )


def test_red_pkg_equals_red_gsfm_when_all_clusters_share_one_variance():
    """§V-A: with equal cluster variances the preloaded gains are the sub-filters' gains."""
    noise = uwb_velocity.synthetic_noise(2, 0.5)
    model = _model(noise, noise)
    run = _simulate(noise, noise, 5, T)
    q, r = model.process_noise, model.measurement_noise
    _, a = _runner("red-gsfm")(q, r, run.zs, run.active)
    _, b = _runner("red-pkg")(q, r, run.zs, run.active)
    np.testing.assert_array_equal(np.asarray(a.extra["active"]), np.asarray(b.extra["active"]))
    np.testing.assert_allclose(
        np.asarray(a.extra["initial"]), np.asarray(b.extra["initial"]), rtol=1e-9, atol=1e-9
    )
    np.testing.assert_allclose(np.asarray(a.mean), np.asarray(b.mean), rtol=1e-9, atol=1e-9)


def test_padded_noise_slots_change_nothing():
    noise = uwb_velocity.synthetic_noise(3, 0.4)
    model = _model(noise, noise)
    run = _simulate(noise, noise, 6, T)
    q, r = model.process_noise, model.measurement_noise
    q7, r7 = gmm.pad(q, 7), gmm.pad(r, 7)
    for method in ("red-gsfm",):
        filt = bank.build_bank(model._replace(process_noise=q7, measurement_noise=r7), method, noise_gain=G)
        _, padded = jax.jit(lambda zs, a: filters.run(filt, zs, _inputs(a)))(run.zs, run.active)
        _, plain = _runner(method)(q, r, run.zs, run.active)
        np.testing.assert_allclose(np.asarray(padded.mean), np.asarray(plain.mean), rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(np.asarray(padded.extra["active"]), np.asarray(plain.extra["active"]))
        assert np.all(np.isfinite(np.asarray(padded.cov)))


@pytest.mark.parametrize(
    "method", ["kf-mm", *(pytest.param(m, marks=pytest.mark.slow) for m in bank.BANK_METHODS if m != "kf-mm")]
)
def test_jit_equals_eager(method):
    noise = uwb_velocity.synthetic_noise(1, 0.3)
    model = _model(noise, noise)
    run = _simulate(noise, noise, 7, T)
    filt = bank.build_bank(model, method, noise_gain=G)
    params = filt.params
    state = filt.init(params)
    eager, eager_ll = [], []
    for k in range(3):
        inp = StepInputs(t=jnp.int32(k + 1), aux=run.active[k])
        state = filt.predict(params, state, inp)
        state, info = filt.update(params, state, run.zs[k], inp)
        eager.append(np.asarray(info.mean))
        eager_ll.append(float(info.loglik))
    _, infos = _runner(method)(model.process_noise, model.measurement_noise, run.zs, run.active)
    np.testing.assert_allclose(np.asarray(infos.mean[:3]), np.array(eager), rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(np.asarray(infos.loglik[:3]), np.array(eager_ll), rtol=1e-11, atol=1e-11)


@functools.cache
def _simulate_batch():
    def sim(c, keys):
        noise = uwb_velocity.synthetic_noise(1, c)
        return jax.vmap(lambda k: uwb_velocity.simulate_labeled(noise, noise, k, n_steps=T))(keys)

    return jax.jit(sim)


def test_matched_rmse_is_at_most_gsf_merge_over_a_sweep():
    """Common random numbers: both filters see the same runs; the per-run MSE difference is paired."""
    n_runs = 150
    keys = jax.random.split(jax.random.key(8), n_runs)
    for c in (0.1, 0.3, 1.0):
        runs = _simulate_batch()(c, keys)
        noise = uwb_velocity.synthetic_noise(1, c)
        model = _model(noise, noise)
        q, r = model.process_noise, model.measurement_noise
        mse = {}
        for method in ("matched", "gsf-merge"):
            mse[method] = np.array(
                [
                    np.mean(
                        np.asarray(
                            _runner(method)(q, r, runs.zs[n], runs.active[n])[1].mean[:, 0]
                            - runs.xs[n, 1:, 0]
                        )
                        ** 2
                    )
                    for n in range(n_runs)
                ]
            )
        d = mse["matched"] - mse["gsf-merge"]
        se = d.std(ddof=1) / np.sqrt(n_runs)
        assert d.mean() <= 3 * se, (c, d.mean(), se)
        if c == 1.0:  # well separated clusters: the oracle is clearly better
            assert d.mean() < -5 * se, (d.mean(), se)


def test_sweep_vmap_over_points_and_runs_equals_a_loop():
    G64 = jnp.asarray(G)

    def make_model(c):
        noise = uwb_velocity.synthetic_noise(1, c)
        return uwb_velocity.rwv_model(noise, noise)

    def simulate(c, key):
        noise = uwb_velocity.synthetic_noise(1, c)
        return uwb_velocity.simulate_labeled(noise, noise, key, n_steps=T)

    cs = jnp.asarray([0.2, 1.0])
    keys = jax.random.split(jax.random.key(10), 3)
    method = "red-gsfr"
    errors = jax.jit(
        lambda cs, keys: bank.sweep_errors(method, make_model, simulate, cs, keys, noise_gain=G64)
    )(cs, keys)
    assert errors.shape == (2, 3, T, 1)
    for p in range(2):
        model = make_model(cs[p])
        for n in range(3):
            run = simulate(cs[p], keys[n])
            _, infos = _runner(method)(model.process_noise, model.measurement_noise, run.zs, run.active)
            np.testing.assert_allclose(
                np.asarray(errors[p, n, :, 0]),
                np.asarray(infos.mean[:, 0] - run.xs[1:, 0]),
                rtol=1e-10,
                atol=1e-10,
            )


@pytest.mark.parametrize("method", ["red-gsfm", pytest.param("gsf-merge", marks=pytest.mark.slow)])
def test_float32_runs_and_agrees_with_float64(method):
    noise = uwb_velocity.synthetic_noise(3, 0.2)
    run = _simulate(noise, noise, 9, T)
    m64 = _model(noise, noise)
    m32 = _model(noise, noise, jnp.float32)
    _, i64 = _runner(method)(m64.process_noise, m64.measurement_noise, run.zs, run.active)
    _, i32 = _runner(method, jnp.float32)(
        m32.process_noise, m32.measurement_noise, run.zs.astype(jnp.float32), run.active
    )
    assert i32.mean.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(i32.mean))) and np.all(np.isfinite(np.asarray(i32.cov)))
    # same selections, estimates to float32 precision of the state's scale (~100)
    if method != "gsf-merge":
        agree = np.mean(np.all(np.asarray(i32.extra["active"]) == np.asarray(i64.extra["active"]), axis=1))
        assert agree >= 0.9, agree
    else:
        np.testing.assert_allclose(np.asarray(i32.mean), np.asarray(i64.mean), rtol=1e-3, atol=1e-3)


def test_steady_state_gains_match_scipy_dare_and_the_riccati_fixed_point():
    g = np.array([DT, 1.0])
    for Q, R in [
        (np.outer(g, g) + 0.01 * np.eye(2), np.eye(1)),
        (48.38 * np.outer(g, g) + 1e-9 * np.eye(2), 3611.99 * np.eye(1)),
    ]:
        K, S = bank.steady_state_gains(
            jnp.asarray(F), jnp.asarray(H), jnp.asarray(Q), jnp.asarray(R), jnp.asarray(PRIOR[1])
        )
        P = _dare(F, H, Q, R)  # SciPy's DARE (first case) or the Riccati iteration to 1e-14 (second)
        S_ref = H @ P @ H.T + R
        np.testing.assert_allclose(np.asarray(S), S_ref, rtol=1e-8)
        np.testing.assert_allclose(np.asarray(K), P @ H.T @ np.linalg.inv(S_ref), rtol=1e-8)


def test_missing_measurement_is_the_moment_matched_prediction():
    noise = uwb_velocity.synthetic_noise(1, 0.5)
    model = _model(noise, noise)
    q, r = model.process_noise, model.measurement_noise
    run = _simulate(noise, noise, 11, T)
    zs = run.zs.at[5].set(jnp.nan)
    for method in ("gsf-merge", "red-gsfr", "matched"):
        states, infos = _runner(method)(q, r, zs, run.active)
        pred = gmm.GaussianMixture(q.weights, states.predicted.means[5], states.predicted.covs[5], q.mask)
        mean, cov = gmm.moments(pred)
        np.testing.assert_allclose(np.asarray(infos.mean[5]), np.asarray(mean), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(infos.cov[5]), np.asarray(cov), rtol=1e-12, atol=1e-12)
        missing, active = infos.extra["missing"], infos.extra["active"]
        assert bool(missing[5]) and list(np.asarray(active[5])) == [-1, -1]
        assert not bool(missing[6]) and np.all(np.isfinite(np.asarray(infos.mean)))
        assert float(infos.loglik[5]) == 0.0 and np.all(np.isfinite(np.asarray(infos.loglik)))


def test_bad_arguments_raise_clear_errors():
    noise = uwb_velocity.synthetic_noise(1, 0.5)
    model = _model(noise, noise)
    with pytest.raises(ValueError, match="method"):
        bank.build_bank(model, "gsf-prune")
    with pytest.raises(ValueError, match="noise_gain"):
        bank.build_bank(model, "red-gsfm", noise_gain=np.ones((3, 1)))
    with pytest.raises(ValueError, match="noise_gain"):
        bank.build_bank(model, "red-gsfm", noise_gain="pca")
    with pytest.raises(ValueError, match="ssg_iterations"):
        bank.build_bank(model, "red-ssg", ssg_iterations=0)
    filt = bank.build_bank(model, "matched")
    inp = StepInputs(t=jnp.int32(1))
    state = filt.predict(filt.params, filt.init(filt.params), inp)
    with pytest.raises(ValueError, match="inputs.aux"):
        filt.update(filt.params, state, jnp.array([0.0]), inp)
    with pytest.raises(ValueError, match="inputs.aux"):
        filt.update(filt.params, state, jnp.array([0.0]), inp._replace(aux=jnp.zeros((3,), jnp.int32)))
    with pytest.raises(ValueError, match="inputs.aux"):
        filters.run(filt, jnp.zeros((5, 1)))  # no active pairs at all
    with pytest.raises(ValueError, match="inputs.aux"):
        filters.run(filt, jnp.zeros((5, 1)), StepInputs(t=jnp.arange(1, 6), aux=jnp.zeros((4, 2), jnp.int32)))
    with pytest.raises(ValueError, match="noise_gain"):
        jax.jit(
            lambda s: (
                bank.build_bank(
                    _model(uwb_velocity.ScalarGM(jnp.ones(1), jnp.zeros(1), s * jnp.ones(1)), noise),
                    "red-gsfm",
                ).params
            )
        )(1.0)


def test_auto_noise_gain_finds_the_noise_line():
    noise = uwb_velocity.synthetic_noise(1, 0.5)
    Gp = bank._resolve_noise_gain("auto", _model(noise, noise).process_noise)
    assert Gp.shape == (1, 2)
    np.testing.assert_allclose(np.abs(np.asarray(Gp)[0]), np.array([DT, 1.0]) / np.hypot(DT, 1.0), rtol=1e-9)


def _eq9_loglik_np(m, P, z, q, r):
    """``log sum_ij w^i p^j N(z; H(F m + u^i) + b^j, H(F P F^T + Q^i)H^T + R^j)`` in NumPy."""
    terms = []
    for wi, ui, Qi in zip(*q):
        mp, Pp = F @ m + ui, F @ P @ F.T + Qi
        for pj, bj, Rj in zip(*r):
            S = H @ Pp @ H.T + Rj
            y = z - H @ mp - bj
            quad = y @ np.linalg.solve(S, y) + np.log(np.linalg.det(2 * np.pi * S))
            terms.append(np.log(wi) + np.log(pj) - 0.5 * quad)
    terms = np.array(terms)
    return terms.max() + np.log(np.sum(np.exp(terms - terms.max())))


@pytest.mark.parametrize("method", ["gsf-merge", "red-gsfm", "kf-mm"])
def test_step_info_loglik_is_the_eq9_normaliser_and_the_fixed_fields(method):
    noise = uwb_velocity.synthetic_noise(3, 0.6)
    model = _model(noise, noise)
    run = _simulate(noise, noise, 12, T)
    q, r = model.process_noise, model.measurement_noise
    states, infos = _runner(method)(q, r, run.zs, run.active)
    qn, rn = _np_noise(q), _np_noise(r)
    if method == "kf-mm":  # one model: the moment-matched noises
        qn = tuple(np.asarray(a)[None] for a in (1.0, *gmm.moments(q)))
        rn = tuple(np.asarray(a)[None] for a in (1.0, *gmm.moments(r)))
    means = np.concatenate([PRIOR[0][None], np.asarray(infos.mean)])
    covs = np.concatenate([PRIOR[1][None], np.asarray(infos.cov)])
    ref = [_eq9_loglik_np(means[k], covs[k], np.asarray(run.zs[k]), qn, rn) for k in range(T)]
    np.testing.assert_allclose(np.asarray(infos.loglik), ref, rtol=1e-10, atol=1e-10)
    assert np.all(np.asarray(infos.n_components) == 1) and infos.n_components.dtype == jnp.int32
    assert not np.any(np.asarray(infos.flags.overflow)) and infos.reduction is None
    assert set(infos.extra) == {"initial", "active", "missing"}
    assert infos.extra["active"].shape == (T, 2) and infos.extra["initial"].shape == (T, 2)


def _perturbed_total(filt, zs, active, objective):
    """``s -> objective(infos)`` with ``s`` added to entry ``(1, 1)`` of the first process-noise cluster."""

    def total(s):
        model = filt.params.model
        q = model.process_noise._replace(covs=model.process_noise.covs.at[0, 1, 1].add(s))
        params = filt.params._replace(model=model._replace(process_noise=q))
        return objective(filters.run(filt, zs, _inputs(active), params=params)[1])

    return total


@pytest.mark.parametrize(
    "method,objective",
    [
        ("gsf-merge", "loglik"),
        ("red-gsfm", "loglik"),
        ("matched", "loglik"),
        ("red-ssg", "initial"),  # through the steady-state gains computed from params in init
    ],
)
def test_grad_wrt_a_process_noise_covariance_matches_central_differences(method, objective):
    noise = uwb_velocity.synthetic_noise(3, 0.6)
    model = _model(noise, noise)
    run = _simulate(noise, noise, 13, T)
    filt = bank.build_bank(model, method, noise_gain=G)
    pick = {"loglik": lambda i: jnp.sum(i.loglik), "initial": lambda i: jnp.sum(i.extra["initial"][:, 0])}
    total = jax.jit(_perturbed_total(filt, run.zs, run.active, pick[objective]))
    g = float(jax.jit(jax.grad(total))(0.0))
    eps = 1e-5
    fd = (float(total(eps)) - float(total(-eps))) / (2 * eps)
    assert np.isfinite(g) and g != 0.0
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-8)


def test_vmap_over_two_parameter_sets_equals_two_runs():
    noise = uwb_velocity.synthetic_noise(2, 0.4)
    model = _model(noise, noise)
    run = _simulate(noise, noise, 14, T)
    filt = bank.build_bank(model, "red-gsfr", noise_gain=G)
    q = model.process_noise
    q2 = q._replace(covs=2.0 * q.covs)
    both = jax.tree_util.tree_map(
        lambda a, b: jnp.stack([a, b]),
        filt.params,
        filt.params._replace(model=filt.params.model._replace(process_noise=q2)),
    )
    _, infos = jax.jit(jax.vmap(lambda p: filters.run(filt, run.zs, _inputs(run.active), params=p)))(both)
    for n, qq in enumerate((q, q2)):
        _, one = _runner("red-gsfr")(qq, model.measurement_noise, run.zs, run.active)
        np.testing.assert_allclose(np.asarray(infos.mean[n]), np.asarray(one.mean), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(
            np.asarray(infos.loglik[n]), np.asarray(one.loglik), rtol=1e-12, atol=1e-12
        )
