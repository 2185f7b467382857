"""Seed 004 helpers: KL to the moment-matched Gaussian, c for a target KL, the labelled simulator.

(The Table I / II scenario objects themselves are tested in test_models.py.)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats

from gmjax import mixture as gmm
from gmjax.scenarios import uwb_velocity


def _scaled(model, c):
    b = uwb_velocity.SYNTHETIC_MODELS[model]
    return uwb_velocity.ScalarGM(b.weights, tuple(c * m for m in b.means), b.variances)


def _kl_scipy(gm):
    w, m, v = (np.asarray(a, float) for a in gm)
    w = w / w.sum()  # Table II's x process weights are rounded (they sum to 0.999)
    mu = w @ m
    var = w @ (v + (m - mu) ** 2)
    s = np.sqrt(v)
    p = lambda x: np.sum(w * stats.norm.pdf(x, m, s))  # noqa: E731
    f = lambda x: p(x) * (np.log(p(x)) - stats.norm.logpdf(x, mu, np.sqrt(var))) if p(x) > 0 else 0.0  # noqa: E731
    pts = sorted(set(np.concatenate([m - 3 * s, m, m + 3 * s]).tolist()))
    lo, hi = np.min(m - 12 * s), np.max(m + 12 * s)
    return integrate.quad(f, lo, hi, points=pts, limit=500, epsabs=1e-12, epsrel=1e-10)[0]


@pytest.mark.parametrize(
    "gm",
    [
        _scaled(1, 0.21),
        _scaled(2, 1.0),
        _scaled(3, 0.096),
        _scaled(3, 3.0),
        uwb_velocity.UWB_NOISES["x"]["process"],
        uwb_velocity.UWB_NOISES["y"]["measurement"],
    ],
)
def test_quadrature_kl_matches_scipy_adaptive_quadrature(gm):
    np.testing.assert_allclose(uwb_velocity.kl_to_moment_matched(gm), _kl_scipy(gm), rtol=1e-7, atol=1e-9)


def test_kl_is_zero_for_one_gaussian_and_mc_agrees_with_quadrature_within_its_standard_error():
    assert abs(uwb_velocity.kl_to_moment_matched(_scaled(1, 0.0))) < 1e-10
    for i, gm in enumerate([_scaled(1, 0.5), _scaled(3, 0.2), uwb_velocity.UWB_NOISES["y"]["process"]]):
        kl_q = uwb_velocity.kl_to_moment_matched(gm)
        kl_mc, se = uwb_velocity.kl_to_moment_matched(
            gm, method="mc", key=jax.random.key(i), return_stderr=True
        )
        assert se > 0 and abs(kl_mc - kl_q) < 4 * se, (kl_mc, kl_q, se)


def test_kl_accepts_a_1d_gaussian_mixture():
    gm = _scaled(2, 0.4)
    mix = gmm.GaussianMixture.create(
        gm.weights, np.array(gm.means)[:, None], np.array(gm.variances)[:, None, None]
    )
    assert uwb_velocity.kl_to_moment_matched(mix) == pytest.approx(
        uwb_velocity.kl_to_moment_matched(gm), rel=1e-12
    )


def test_paper_fig5_scales_give_kl_about_one_half():
    """Fig. 5: c = 0.21, 0.215, 0.096 give "an approximate KL divergence of 0.5" (c has 2-3 digits)."""
    for model, c in [(1, 0.21), (2, 0.215), (3, 0.096)]:
        assert abs(uwb_velocity.kl_curve(model, [c])[0] - 0.5) < 0.05


def test_c_for_kl_inverts_the_quadrature_kl():
    for model in (1, 2, 3):
        for kl in (0.0, 0.3, 1.5, 4.0):
            c = uwb_velocity.c_for_kl(model, kl)
            assert uwb_velocity.kl_curve(model, [c])[0] == pytest.approx(kl, abs=1e-8)
    assert uwb_velocity.c_for_kl(1, 0.5) < uwb_velocity.c_for_kl(1, 1.0)


def test_bad_kl_arguments():
    with pytest.raises(ValueError, match="method"):
        uwb_velocity.kl_to_moment_matched(_scaled(1, 1.0), method="simpson")
    with pytest.raises(ValueError, match="key"):
        uwb_velocity.kl_to_moment_matched(_scaled(1, 1.0), method="mc")
    with pytest.raises(ValueError, match="variances"):
        uwb_velocity.kl_to_moment_matched(uwb_velocity.ScalarGM((1.0,), (0.0,), (0.0,)))
    with pytest.raises(ValueError, match="gm"):
        uwb_velocity.kl_to_moment_matched([1.0, 2.0])
    with pytest.raises(ValueError, match="kl"):
        uwb_velocity.c_for_kl(1, -1.0)
    with pytest.raises(ValueError, match="kl"):
        uwb_velocity.c_for_kl(1, 50.0)
    with pytest.raises(ValueError, match="model"):
        uwb_velocity.c_for_kl(4, 1.0)


def test_rwv_model_equals_the_validated_scenario_model():
    gm = _scaled(3, 0.7)
    a = uwb_velocity.synthetic(3, 0.7).model
    b = uwb_velocity.rwv_model(gm, gm)
    for x, y in [
        (a.process_noise, b.process_noise),
        (a.measurement_noise, b.measurement_noise),
        (a.prior, b.prior),
    ]:
        for u, v in zip(x, y):
            np.testing.assert_allclose(np.asarray(u), np.asarray(v), rtol=1e-12, atol=1e-15)
    x = jnp.array([1.0, 2.0])
    np.testing.assert_allclose(a.f(x, 1), b.f(x, 1))
    np.testing.assert_allclose(a.h(x, 1), b.h(x, 1))


def test_labelled_simulator_draws_each_noise_from_its_labelled_cluster():
    gm = uwb_velocity.UWB_NOISES["x"]["process"], uwb_velocity.UWB_NOISES["x"]["measurement"]
    n_runs, T = 400, 50
    runs = jax.jit(jax.vmap(lambda k: uwb_velocity.simulate_labeled(*gm, k, n_steps=T)))(
        jax.random.split(jax.random.key(3), n_runs)
    )
    xs, zs, act = (np.asarray(a) for a in runs)
    Fm = np.array([[1.0, uwb_velocity.DT], [0.0, 1.0]])
    v = xs[:, 1:] - xs[:, :-1] @ Fm.T  # (N, T, 2)
    np.testing.assert_allclose(v[..., 0], uwb_velocity.DT * v[..., 1], rtol=1e-9, atol=1e-9)  # eq 20
    w = zs[..., 0] - xs[:, 1:, 0]
    n = n_runs * T
    for draws, labels, table in ((v[..., 1], act[..., 0], gm[0]), (w, act[..., 1], gm[1])):
        wts, means, var = (np.asarray(a) for a in table)
        freq = np.bincount(labels.ravel(), minlength=len(wts)) / n
        assert np.all(np.abs(freq - wts / wts.sum()) < 5 * np.sqrt(wts * (1 - wts) / n) + 1e-12)
        z = (draws - means[labels]) / np.sqrt(var[labels])  # standardised within the labelled cluster
        assert abs(z.mean()) < 5 / np.sqrt(n) and abs(z.var() - 1) < 5 * np.sqrt(2 / n)
    # x_0 ~ N(0, 100 I)
    assert abs(xs[:, 0].var(axis=0) / 100 - 1).max() < 5 * np.sqrt(2 / n_runs)


def test_synthetic_noise_traces_in_c():
    means = jax.jit(lambda c: uwb_velocity.synthetic_noise(2, c).means)(2.0)
    np.testing.assert_allclose(np.asarray(means), 2.0 * np.array([-50, -30, 0, 30, 50]))
    with pytest.raises(ValueError, match="model"):
        uwb_velocity.synthetic_noise(0, 1.0)
    np.testing.assert_allclose(np.asarray(uwb_velocity.noise_gain())[:, 0], [uwb_velocity.DT, 1.0])


def test_benchmark_rmse_is_eq23_per_run_averaged_over_runs_with_pooled_beside_it():
    """bench_seed004 reports eq 23 per run, averaged (Figs 2-4); checked against a plain per-run loop."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_seed004 import _paired_vs, _scores

    rng = np.random.default_rng(0)
    # runs with very different error scales, so the two averages differ clearly
    errors = rng.normal(size=(2, 6, 9, 1)) * rng.uniform(0.1, 5.0, size=(2, 6, 1, 1))
    got = _scores(errors)
    for p in range(2):
        per_run = [np.sqrt(sum(float(e) ** 2 for e in errors[p, n, :, 0]) / 9) for n in range(6)]
        assert got["rmse"][p] == pytest.approx(np.mean(per_run), rel=1e-12)
        assert got["rmse_se"][p] == pytest.approx(np.std(per_run, ddof=1) / np.sqrt(6), rel=1e-12)
        pooled = np.sqrt(np.mean(errors[p, ..., 0] ** 2))
        assert got["rmse_pooled"][p] == pytest.approx(pooled, rel=1e-12)
        assert got["rmse"][p] < got["rmse_pooled"][p]  # Jensen: mean of roots <= root of mean
        cep_run = [np.median(np.abs(errors[p, n, :, 0])) for n in range(6)]
        assert got["cep"][p] == pytest.approx(np.mean(cep_run), rel=1e-12)
        assert got["cep_pooled"][p] == pytest.approx(np.median(np.abs(errors[p])), rel=1e-12)
    rmse_run = {
        m: rng.uniform(1, 2, size=(2, 6))
        for m in ("gsf-merge", "red-gsfm", "red-gsfr", "red-pkg", "red-ssg", "red-dkg")
    }
    paired = _paired_vs(rmse_run)
    d = rmse_run["red-ssg"] - rmse_run["gsf-merge"]
    np.testing.assert_allclose(paired["red-ssg"]["diff"], d.mean(axis=1), rtol=1e-12)
    np.testing.assert_allclose(paired["red-ssg"]["se"], d.std(axis=1, ddof=1) / np.sqrt(6), rtol=1e-12)
