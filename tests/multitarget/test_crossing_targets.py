"""The crossing-targets scenario (issue 47): its numbers, its crossings, its simulation, and a smoke run of
``benchmarks/bench_cphd.py``'s study on a tiny configuration."""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import multitarget as mt

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))


def _true_positions(sc):
    """``(T, N, 2)`` the tracks' positions by the CV recursion in NumPy (NaN where not alive)."""
    x0 = np.asarray(sc.initial_states)
    births, deaths = np.asarray(sc.birth_times), np.asarray(sc.death_times)
    k = np.arange(1, sc.n_steps + 1)[:, None]
    pos = x0[None, :, :2] + (k - births)[..., None] * x0[None, :, 2:]
    alive = (births <= k) & (k < deaths)
    return np.where(alive[..., None], pos, np.nan), alive


def test_builder_numbers():
    sc = mt.crossing_targets()
    assert sc.name == "crossing_targets" and sc.n_steps == 100
    assert sc.n_targets == 8 and sc.initial_states.shape == (8, 4)
    assert sc.birth.capacity == 4 and bool(np.all(np.asarray(sc.birth.mask)))
    np.testing.assert_allclose(np.asarray(sc.birth.weights), 0.03)
    np.testing.assert_allclose(np.asarray(sc.birth.means)[:, 2:], 0.0)
    # every track starts at one of the birth sites, and every site is used
    sites = np.asarray(sc.birth.means)[:, :2]
    starts = np.asarray(sc.initial_states)[:, :2]
    hits = np.all(np.isclose(starts[:, None, :], sites[None, :, :]), axis=-1)
    assert np.all(hits.sum(1) == 1) and np.all(hits.sum(0) >= 1)
    assert sc.detection_prob == 0.9 and sc.clutter_rate == 30.0 and sc.survival_prob == 0.99
    assert sc.max_measurements == mt.clutter_capacity(30.0, 8) == 128
    lo, hi = (np.asarray(a) for a in sc.region)
    np.testing.assert_array_equal(lo, [-1000.0, -1000.0])
    np.testing.assert_array_equal(hi, [1000.0, 1000.0])
    assert sc.clutter_density == pytest.approx(1.0 / 4e6)
    np.testing.assert_array_equal(np.asarray(sc.birth_times), [1, 1, 10, 20, 30, 40, 50, 60])
    # the same single-target model as vo_ma_linear
    ref = mt.vo_ma_linear()
    for a, b in (
        (sc.model.process_noise, ref.model.process_noise),
        (sc.model.measurement_noise, ref.model.measurement_noise),
    ):
        np.testing.assert_allclose(np.asarray(a.covs), np.asarray(b.covs))
    x = jnp.arange(4.0)
    np.testing.assert_allclose(sc.model.f(x, 1), ref.model.f(x, 1))
    np.testing.assert_allclose(sc.model.h(x, 1), ref.model.h(x, 1))
    assert "crossing" in sc.description
    # arguments pass through
    other = mt.crossing_targets(
        clutter_rate=5.0, detection_prob=0.8, n_steps=40, max_measurements=16, dtype=jnp.float32
    )
    assert other.clutter_rate == 5.0 and other.detection_prob == 0.8 and other.n_steps == 40
    assert other.max_measurements == 16 and other.initial_states.dtype == jnp.float32
    assert mt.crossing_targets(clutter_rate=5.0).max_measurements == mt.clutter_capacity(5.0, 8)


def test_tracks_cross_in_the_middle_and_stay_in_the_region():
    sc = mt.crossing_targets()
    pos, alive = _true_positions(sc)
    counts = alive.sum(1)
    assert counts.max() == 8 and counts[0] == 2 and counts[-1] == 5
    assert np.nanmax(np.abs(pos)) < 1000.0
    crossings = []
    for i in range(8):
        for j in range(i + 1, 8):
            d = np.linalg.norm(pos[:, i] - pos[:, j], axis=-1)
            if np.nanmin(d) < 50.0:
                k = int(np.nanargmin(d))
                crossings.append((i, j))
                assert np.all(np.abs(pos[k, i]) <= 200.0)  # in the middle of the region
    assert len(crossings) in (2, 3)


def test_simulate_short_run_has_no_overflow_at_the_default_capacity():
    sc = mt.crossing_targets(n_steps=20)
    s = jax.jit(jax.vmap(lambda k: mt.simulate(sc, k)))(jax.random.split(jax.random.PRNGKey(3), 4))
    assert s.zs.shape == (4, 20, sc.max_measurements, 2)
    assert not bool(np.any(np.asarray(s.overflow)))
    alive = np.asarray(s.alive)
    _, ref_alive = _true_positions(sc)
    np.testing.assert_array_equal(alive, np.broadcast_to(ref_alive, alive.shape))
    n_valid = np.isfinite(np.asarray(s.zs)).all(-1).sum(-1)
    np.testing.assert_array_equal(n_valid, np.asarray(s.detected).sum(-1) + np.asarray(s.n_clutter))
    # deterministic tracks: the true states are the CV recursion's
    pos, _ = _true_positions(sc)
    np.testing.assert_allclose(np.asarray(s.states[0])[..., :2], np.nan_to_num(pos), atol=1e-9)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"clutter_rate": -1.0}, "clutter_rate"),
        ({"clutter_rate": float("nan")}, "clutter_rate"),
        ({"detection_prob": 0.0}, "detection_prob"),
        ({"detection_prob": 1.5}, "detection_prob"),
        ({"n_steps": 0}, "n_steps"),
        ({"n_steps": 10.5}, "n_steps"),
        ({"max_measurements": 0}, "max_measurements"),
        ({"max_measurements": True}, "max_measurements"),
    ],
)
def test_bad_arguments_raise(kwargs, name):
    with pytest.raises(ValueError, match=name):
        mt.crossing_targets(**kwargs)


@pytest.mark.slow  # ~17-21 s on the shared 2-core machine (compiling both filters and OSPA)
def test_bench_cphd_core_runs_on_a_tiny_configuration():
    import bench_cphd

    sc = mt.crossing_targets(n_steps=5, clutter_rate=5.0, max_measurements=16)
    res = bench_cphd.run_study(sc, runs=2, seed=0, capacity=10, merge_capacity=40, n_max=20, burn_in=1)
    assert res["runs"] == 2 and res["steps"] == 5 and res["window"] == [2, 5]
    for k in bench_cphd.ESTIMATORS:
        assert np.isfinite(res["cardinality"][k]["var"]) and np.isfinite(res["cardinality"][k]["bias"])
    for name in ("phd", "cphd"):
        assert np.isfinite(res["ospa"][name]["mean"])
        assert res["timing"][name]["compile_s"] > 0 and res["timing"][name]["us_per_run_scan"] > 0
    assert len(res["series"]["ospa_cphd"]) == 5
    assert "crossing_targets" in bench_cphd.verdict(res)
    md = "\n".join(bench_cphd.scenario_markdown(res))
    assert "CPHD MAP count" in md


def test_jackknife_se_of_the_mean_is_the_usual_standard_error():
    import bench_cphd

    x = np.random.default_rng(0).normal(size=30)
    se = bench_cphd.jackknife_se(lambda sel: float(x[sel].mean()), 30)
    assert se == pytest.approx(x.std(ddof=1) / np.sqrt(30))
    assert np.isnan(bench_cphd.jackknife_se(lambda sel: 0.0, 2))
