"""The GM-LMB filter (gmjax.multitarget.lmb) against the NumPy reference, the exact enumeration of the
association hypotheses, and the usual jit/vmap/dtype/gradient checks."""

import re
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gmjax.multitarget as mt
from gmjax import mixture as gmm
from gmjax import reduction
from gmjax.filters.base import StepInputs
from gmjax.filters.local import gaussian_moments, local_filter_for
from gmjax.multitarget import hypotheses as hyp
from gmjax.multitarget import lmb
from references import lmb_np as ref

T, J, G = 10, 4, 80  # track slots, components per track, Gibbs rows


def _scenario(n_steps=10, clutter_rate=8.0):
    return mt.vo_ma_linear(n_steps=n_steps, clutter_rate=clutter_rate, max_measurements=24)


def _filter(sc, **kw):
    kw = dict(capacity=T, components_per_track=J, n_samples=G) | kw
    return lmb.gm_lmb(sc.model, **sc.filter_kwargs(), **kw)


def _linear(model):
    x0 = jnp.zeros(model.state_dim)
    F = np.asarray(jax.jacfwd(lambda x: model.f(x, 1))(x0))
    H = np.asarray(jax.jacfwd(lambda x: model.h(x, 1))(x0))
    return (
        F,
        np.asarray(gaussian_moments(model.process_noise)[1]),
        H,
        np.asarray(gaussian_moments(model.measurement_noise)[1]),
    )


def _as_ref(state) -> ref.Tracks:
    s = jax.tree_util.tree_map(np.asarray, state)
    d = s.density
    return ref.Tracks(s.existence, s.labels.astype(np.int64), s.mask, d.weights, d.means, d.covs, d.mask)


def _assert_tracks_equal(ours, theirs: ref.Tracks, rtol=1e-9):
    o = _as_ref(ours)
    np.testing.assert_array_equal(o.mask, theirs.mask)
    np.testing.assert_array_equal(o.labels, theirs.labels)
    np.testing.assert_array_equal(o.cmask, theirs.cmask)
    np.testing.assert_allclose(o.r, theirs.r, rtol=rtol, atol=1e-14)
    np.testing.assert_allclose(o.w, theirs.w, rtol=rtol, atol=1e-13)
    np.testing.assert_allclose(o.m, theirs.m, rtol=rtol, atol=1e-9)
    np.testing.assert_allclose(o.P, theirs.P, rtol=rtol, atol=1e-9)


def test_every_step_equals_the_numpy_reference():
    """Predict, the costs, every Gibbs row, the distinct rows, ``r'``, ``beta``, the posterior tracks,
    the log-likelihood and the labelled estimates, step by step, with the same draws."""
    sc = _scenario()
    sample = mt.simulate(sc, jax.random.key(3))
    f = _filter(sc)
    params = f.params
    lf = local_filter_for(sc.model, "kf")
    F, Q, H, R = _linear(sc.model)
    birth = jax.tree_util.tree_map(np.asarray, params.birth)
    kw = dict(n_tracks=T, n_components=J, existence_threshold=1e-3, component_threshold=1e-5)

    predict = jax.jit(lambda s: lmb.predict_tracks(lf, params, s, jnp.asarray(1)))
    update = jax.jit(lambda s, z, u: lmb.update_tracks(lf, params, s, z, jnp.asarray(1), u, n_tracks=T))
    state, theirs = f.init(params), ref.empty_tracks(T, J, 4)
    keys = jax.random.split(jax.random.key(7), sc.n_steps)
    n_hyp = []
    for k in range(sc.n_steps):
        pred = predict(state)
        their_pred = ref.predict(
            theirs, F, Q, sc.survival_prob, birth.weights, birth.means, birth.covs, birth.mask, k + 1
        )
        _assert_tracks_equal(pred, their_pred)
        u = hyp.gibbs_uniforms(keys[k], G - 1, pred.existence.shape[0], jnp.float64)
        upd = update(pred, sample.zs[k], u)
        res = ref.update(
            their_pred, np.asarray(sample.zs[k]), H, R, sc.detection_prob, sc.clutter_rate,
            sc.clutter_density, np.asarray(u), **kw,
        )  # fmt: skip
        np.testing.assert_array_equal(np.asarray(upd.samples), res.samples)
        np.testing.assert_array_equal(np.asarray(upd.distinct), res.kept)
        np.testing.assert_allclose(upd.existence, res.r, rtol=1e-9, atol=1e-14)
        np.testing.assert_allclose(upd.association, res.beta, rtol=1e-9, atol=1e-14)
        np.testing.assert_allclose(float(upd.loglik), res.loglik, rtol=1e-10)
        assert bool(upd.overflow) == res.overflow and not bool(upd.degenerate)
        _assert_tracks_equal(upd.tracks, res.tracks)
        est, their_est = lmb.extract_tracks(upd.tracks, max_estimates=T), ref.extract(res.tracks, T)
        assert int(est.n_estimates) == their_est.n_hat
        np.testing.assert_array_equal(np.asarray(est.mask), their_est.mask)
        np.testing.assert_array_equal(np.asarray(est.labels), their_est.labels)
        np.testing.assert_allclose(est.states, their_est.states, rtol=1e-9, atol=1e-9)
        n_hyp.append(int(np.sum(res.kept)))
        state, theirs = upd.tracks, res.tracks
    assert max(n_hyp) > 2 and int(np.sum(state.mask)) >= 2  # real association problems, live tracks


def test_the_filter_update_is_update_tracks_with_the_key_s_draws():
    sc = _scenario(n_steps=3)
    sample = mt.simulate(sc, jax.random.key(0))
    f = _filter(sc)
    lf = local_filter_for(sc.model, "kf")
    inputs = StepInputs(t=jnp.asarray(1))
    pred = f.predict(f.params, f.init(f.params), inputs)
    key = jax.random.key(5)
    post, info = jax.jit(partial(f.update, key=key))(f.params, pred, sample.zs[0], inputs)
    u = hyp.gibbs_uniforms(key, G - 1, T + f.params.birth.capacity, jnp.float64)
    upd = lmb.update_tracks(lf, f.params, pred, sample.zs[0], inputs.t, u, n_tracks=T)
    for a, b in zip(jax.tree_util.tree_leaves(post), jax.tree_util.tree_leaves(upd.tracks)):
        np.testing.assert_array_equal(a, b)
    assert float(info.loglik) == float(upd.loglik)
    np.testing.assert_allclose(info.extra["cardinality"], np.sum(np.asarray(post.existence)), rtol=1e-14)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_distinct_drawn_hypotheses_give_the_exact_update_when_they_are_all_drawn(seed):
    """Three tracks, three measurements (86 hypotheses): enough Gibbs rows visit every one, and the
    truncated marginals are the exact ones of the enumeration; few rows give a lower normaliser."""
    rng = np.random.default_rng(seed)
    N, M = 3, 3
    r = rng.uniform(0.4, 0.7, N)  # costs of one order of magnitude: every hypothesis gets drawn
    p_d = 0.6
    det = np.log(r[:, None] * p_d * rng.uniform(0.5, 2.0, (N, M)))
    log_eta = np.concatenate([np.log1p(-r)[:, None], np.log(r * (1 - p_d))[:, None], det], axis=1)
    exact = ref.exact_marginals(log_eta)
    uniforms = hyp.gibbs_uniforms(jax.random.key(seed), 2999, N, jnp.float64)
    samples = hyp.gibbs_sample(jnp.asarray(log_eta), jnp.ones(N, bool), uniforms)
    distinct = hyp.distinct_rows(samples)
    _, r_post, beta, log_norm = hyp.hypothesis_marginals(jnp.asarray(log_eta), samples, distinct)
    assert int(np.sum(distinct)) == exact.n_hypotheses == 86
    np.testing.assert_allclose(r_post, exact.r, rtol=1e-12)
    np.testing.assert_allclose(beta, exact.beta, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(float(log_norm), exact.log_norm, rtol=1e-13)
    # no measurement twice, and the same rows as the reference's sampler
    rows = np.asarray(samples)
    for row in rows:
        det_used = row[row >= 2]
        assert len(det_used) == len(set(det_used.tolist()))
    np.testing.assert_array_equal(rows, ref.gibbs(log_eta, np.ones(N, bool), np.asarray(uniforms)))
    few = hyp.distinct_rows(samples[:6])
    assert float(hyp.hypothesis_marginals(jnp.asarray(log_eta), samples[:6], few)[3]) < exact.log_norm


def _run(f, zs, key, params=None):
    return mt.run(f, zs, key=key, params=params)


def test_jit_eager_vmap_loop_and_float32():
    sc = _scenario(n_steps=8)
    keys = jax.random.split(jax.random.key(11), 2)
    samples = jax.vmap(lambda k: mt.simulate(sc, k))(keys)
    f = _filter(sc)
    run_keys = jax.random.split(jax.random.key(12), 2)
    eager = [_run(f, samples.zs[i], run_keys[i]) for i in range(2)]
    jitted = jax.jit(partial(_run, f))(samples.zs[0], run_keys[0])
    batched = jax.jit(jax.vmap(partial(_run, f)))(samples.zs, run_keys)
    for a, b in zip(jax.tree_util.tree_leaves(eager[0]), jax.tree_util.tree_leaves(jitted)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    for i in range(2):
        for a, b in zip(jax.tree_util.tree_leaves(eager[i]), jax.tree_util.tree_leaves(batched)):
            np.testing.assert_allclose(a, b[i], rtol=1e-9, atol=1e-9)
    # float32: the same draws (on the 2^-24 grid); the same labels and cardinalities on this run
    sc32 = mt.vo_ma_linear(n_steps=8, clutter_rate=8.0, max_measurements=24, dtype=jnp.float32)
    f32 = _filter(sc32)
    _, i32 = _run(f32, samples.zs[0].astype(jnp.float32), run_keys[0])
    _, i64 = eager[0]
    assert i32.loglik.dtype == jnp.float32 and i32.extra["estimates"].dtype == jnp.float32
    np.testing.assert_array_equal(i32.extra["estimate_labels"], i64.extra["estimate_labels"])
    np.testing.assert_allclose(i32.extra["cardinality"], i64.extra["cardinality"], rtol=1e-3)
    np.testing.assert_allclose(i32.extra["estimates"], i64.extra["estimates"], rtol=1e-4, atol=1e-2)


def test_loglik_gradient_in_clutter_rate_and_detection_prob_matches_central_differences():
    """With the key fixed, the drawn hypotheses are locally constant in the parameters, so ``jax.grad``
    of the summed log-likelihood is the truncated update's derivative: central differences agree."""
    sc = _scenario(n_steps=5)
    sample = mt.simulate(sc, jax.random.key(2))
    f = _filter(sc)
    key = jax.random.key(4)

    def total(theta):
        p = f.params._replace(clutter_rate=theta[0], detection_prob=theta[1])
        _, info = _run(f, sample.zs, key, p)
        return jnp.sum(info.loglik)

    theta = jnp.array([sc.clutter_rate, 0.9])
    g = jax.jit(jax.grad(total))(theta)
    h = 1e-6
    value = jax.jit(total)
    fd = [(value(theta + h * e) - value(theta - h * e)) / (2 * h) for e in jnp.eye(2)]
    assert np.all(np.isfinite(g)) and np.all(np.asarray(g) != 0)
    np.testing.assert_allclose(g, fd, rtol=1e-5)


def test_tracks_keep_their_labels_on_the_vo_ma_scenario():
    """Every estimate carries the label it was born with: no label switch on this run, births labelled
    by their birth step, and the estimated cardinality follows the truth after a step or two."""
    sc = mt.vo_ma_linear(n_steps=30, clutter_rate=10.0)
    sample = mt.simulate(sc, jax.random.key(0))
    f = lmb.gm_lmb(sc.model, **sc.filter_kwargs(), capacity=20, components_per_track=5, n_samples=200)
    _, info = jax.jit(partial(_run, f))(sample.zs, jax.random.key(1))
    ex = info.extra
    switches = mt.tracks.label_switches(
        sample.states, sample.alive, ex["estimates"], ex["estimate_labels"], ex["estimate_mask"], gate=50.0
    )
    assert switches.total == 0
    truth = np.asarray(sample.alive).sum(1)
    assert np.mean(np.asarray(ex["n_estimates"]) == truth) > 0.85
    labels = np.asarray(ex["estimate_labels"])[np.asarray(ex["estimate_mask"])]
    assert {tuple(x) for x in labels} >= {(1, 0), (1, 1), (20, 0)}  # the scenario's births at 1, 1, 20
    ospa2 = mt.tracks.ospa2(
        sample.states, sample.alive, ex["estimates"], ex["estimate_labels"], ex["estimate_mask"], cutoff=100.0
    )
    assert ospa2.shape == (30,) and np.all(ospa2 >= 0) and np.all(ospa2 <= 100.0)
    assert not np.any(np.asarray(info.flags.overflow)) and not np.any(np.asarray(info.flags.degenerate))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(clutter_rate=0.0), "clutter_rate"),
        (dict(n_samples=0), "n_samples"),
        (dict(capacity=1.5), "capacity"),
        (dict(components_per_track=0), "components_per_track"),
        (dict(existence_threshold=1.0), "existence_threshold"),
        (dict(detection_prob=0.0), "detection_prob"),
        (dict(local="nope"), "local"),
    ],
)
def test_bad_arguments_name_themselves(kwargs, match):
    sc = _scenario(n_steps=2)
    with pytest.raises(ValueError, match=match):
        lmb.gm_lmb(sc.model, **(sc.filter_kwargs() | kwargs))


def test_birth_weights_must_be_existence_probabilities_and_a_key_is_needed():
    sc = _scenario(n_steps=2)
    birth = sc.birth._replace(weights=sc.birth.weights.at[0].set(1.5))
    with pytest.raises(ValueError, match="birth"):
        lmb.gm_lmb(sc.model, **(sc.filter_kwargs() | dict(birth=birth)))
    sample = mt.simulate(sc, jax.random.key(0))
    with pytest.raises(ValueError, match="key"):
        mt.run(_filter(sc), sample.zs)
    # one Gibbs row (every track missed) needs no key
    _, info = mt.run(_filter(sc, n_samples=1), sample.zs)
    assert np.all(np.asarray(info.extra["n_hypotheses"]) == 1)


# the code block of the GM-LMB section of docs/reproductions/phd.md, verbatim (that page is not run by
# tests/test_docs_examples.py, so it runs here; the test checks the page still shows this code)
DOCS_PAGE = Path(__file__).resolve().parents[2] / "docs" / "reproductions" / "phd.md"
DOCS_SNIPPET = """\
import jax
from gmjax import multitarget as mt

scenario = mt.vo_ma_linear(n_steps=20, max_measurements=24)
sample = mt.simulate(scenario, jax.random.PRNGKey(0))
lmb = mt.gm_lmb(scenario.model, **scenario.filter_kwargs(), capacity=20, n_samples=200)
states, infos = mt.run(lmb, sample.zs, key=jax.random.PRNGKey(1))
est = infos.extra
print(est["n_estimates"], sample.alive.sum(-1))
print(est["estimate_labels"][-1][est["estimate_mask"][-1]])  # (birth step, birth slot) of each track
switches = mt.label_switches(
    sample.states, sample.alive, est["estimates"], est["estimate_labels"], est["estimate_mask"]
)
ospa2 = mt.ospa2(sample.states, sample.alive, est["estimates"], est["estimate_labels"], est["estimate_mask"])
print(switches.total, ospa2[-1])
"""


def test_docs_snippet_runs():
    blocks = re.findall(r"^```python\n(.*?)^```", DOCS_PAGE.read_text(), flags=re.S | re.M)
    assert DOCS_SNIPPET in blocks
    namespace: dict = {}
    exec(compile(DOCS_SNIPPET, str(DOCS_PAGE), "exec"), namespace)
    est, sample, switches = namespace["est"], namespace["sample"], namespace["switches"]
    assert np.mean(np.asarray(est["n_estimates"]) == np.asarray(sample.alive).sum(-1)) > 0.8
    assert switches.total == 0 and np.all(np.isfinite(namespace["ospa2"]))


def test_a_reducer_per_track_merges_and_preserves_each_track_s_moments():
    """``reducer=Runnalls(num_out=2)``: each track's ``(1 + M) J`` updated components are merged to two
    (moment-preserving merges), so every track's mean and covariance equal those of the same update
    keeping every component; a reducer that merges nothing changes nothing."""
    sc = _scenario(n_steps=2)
    sample = mt.simulate(sc, jax.random.key(1))
    M = sample.zs.shape[1]
    lf = local_filter_for(sc.model, "kf")
    inputs = StepInputs(t=jnp.asarray(1))
    key = jax.random.key(3)
    everything = _filter(sc, components_per_track=1 + M, component_threshold=0.0)
    merged = _filter(sc, reducer=reduction.Runnalls(num_out=2), component_threshold=0.0)
    untouched = _filter(sc, reducer=reduction.Runnalls(num_out=(1 + M) * J))

    def one_update(f):
        pred = f.predict(f.params, f.init(f.params), inputs)  # step 1: the births, one component each
        u = hyp.gibbs_uniforms(key, G - 1, pred.existence.shape[0], jnp.float64)
        return jax.jit(lambda p, z: lmb.update_tracks(lf, f.params, p, z, inputs.t, u, n_tracks=T))(
            pred, sample.zs[0]
        )

    full, red = one_update(everything).tracks, one_update(merged).tracks
    np.testing.assert_array_equal(red.mask, full.mask)
    np.testing.assert_allclose(red.existence, full.existence, rtol=1e-12)
    assert np.all(np.asarray(red.density.mask).sum(1) <= 2) and np.any(
        np.asarray(full.density.mask).sum(1) > 2
    )
    for i in np.flatnonzero(np.asarray(full.mask)):
        track = lambda s: jax.tree_util.tree_map(lambda a: a[i], s.density)  # noqa: E731
        for a, b in zip(gmm.moments(track(red)), gmm.moments(track(full))):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)
    plain, same = one_update(_filter(sc)).tracks, one_update(untouched).tracks
    for a, b in zip(jax.tree_util.tree_leaves(plain), jax.tree_util.tree_leaves(same)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)


def test_init_with_a_prior_makes_one_track_per_component():
    sc = _scenario(n_steps=2)
    f = _filter(sc)
    prior = sc.birth._replace(weights=jnp.asarray([0.9, 0.4]))
    state = f.init(f.params, prior)
    np.testing.assert_array_equal(state.mask, np.arange(T) < 2)
    np.testing.assert_allclose(state.existence[:2], [0.9, 0.4])
    np.testing.assert_array_equal(state.labels[:2], [[0, 0], [0, 1]])
    np.testing.assert_allclose(state.density.means[:2, 0], sc.birth.means)
    assert np.all(np.asarray(state.density.mask).sum(1) == (np.arange(T) < 2))
