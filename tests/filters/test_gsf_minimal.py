"""The minimal PCM-GSF kernel of references/gsf_minimal.py against gmjax (issue 17).

The benchmark ``bench_gsf_kernel.py`` reports gmjax / minimal for PCM-GSF (grid) only if both compute
the same thing; these tests are that check both ways: the reduction alone on random mixtures with
many overlapping clusters (every output component equal, in the same order), and whole filter runs
of the seed 000 1-D jump system and the 4-D range-bearing system (estimates equal to 1e-9).
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from bench_gsf_kernel import _log_mix  # noqa: E402

from gmjax import GaussianMixture  # noqa: E402
from gmjax.filters import run  # noqa: E402
from gmjax.filters.gsf import build_gsf  # noqa: E402
from gmjax.models.base import simulate  # noqa: E402
from gmjax.reduction import PCM  # noqa: E402
from gmjax.scenarios.glint_range_bearing import range_bearing  # noqa: E402
from gmjax.scenarios.jump_system import jump_system  # noqa: E402
from references import gsf_minimal  # noqa: E402

PCM_ARGS = (0.9544, 1e-3, (1.0, 3.0), 11, 0.5)  # rho, alpha, lambda range, grid size, range scale


@pytest.mark.parametrize(
    "d, dims", [(1, None), (2, None), pytest.param(3, (0, 2), marks=pytest.mark.slow)]
)  # 3-D: Cholesky paths and clustering dims, also covered by the 4-D filter test
def test_minimal_pcm_reduction_equals_gmjax(d, dims):
    """60 components, 45 live (the rest -inf), into 20: crowded means so most clusters overlap."""
    n, k, n_mix = 60, 20, 64
    rng = np.random.default_rng(7 + d)
    w = rng.dirichlet(np.full(n, 0.7), n_mix) * (np.arange(n) < 45)
    w /= w.sum(1, keepdims=True)
    m = rng.normal(size=(n_mix, n, d)) * 1.5
    A = rng.normal(size=(n_mix, n, d, d)) * 0.6
    P = A @ np.swapaxes(A, -1, -2) + 0.3 * np.eye(d)
    live = w > 0
    with np.errstate(divide="ignore"):
        log_w = np.where(live, np.log(np.where(live, w, 1.0)), -np.inf)
    gm = GaussianMixture(jnp.asarray(w), jnp.asarray(m), jnp.asarray(P), jnp.asarray(live))

    reducer = PCM(max_components=k, capacity=k, dims=dims, newton_steps=0)
    out, info = jax.jit(jax.vmap(lambda g: reducer(g)))(gm)
    mine = jax.jit(
        jax.vmap(
            lambda a, b, c: gsf_minimal._pcm(a, b, c, k, *PCM_ARGS, None if dims is None else list(dims))
        )
    )
    lw, mu, cov = (np.asarray(a) for a in mine(jnp.asarray(log_w), jnp.asarray(m), jnp.asarray(P)))

    n_clusters = np.asarray(info.n_out)
    assert n_clusters.min() >= 1 and (n_clusters < np.asarray(info.aux["n_reference"])).mean() > 0.5
    for b in range(n_mix):
        on = np.isfinite(lw[b])  # minimal: slot = cluster head; gmjax: the heads compacted in order
        c = int(n_clusters[b])
        assert on.sum() == c
        np.testing.assert_allclose(np.exp(lw[b][on]), np.asarray(out.weights[b, :c]), rtol=1e-12, atol=0)
        np.testing.assert_allclose(mu[b][on], np.asarray(out.means[b, :c]), rtol=0, atol=1e-10)
        np.testing.assert_allclose(cov[b][on], np.asarray(out.covs[b, :c]), rtol=0, atol=1e-10)


def _filter_runs(sc, dims, n_runs):
    model, K = sc.model, 20
    keys = jax.random.split(jax.random.key(3), n_runs)
    _, zs, ts = jax.jit(jax.vmap(lambda key: simulate(sc, key)))(keys)
    ts = ts[0]
    minimal = gsf_minimal.minimal_gsf(
        model.f,
        model.h,
        _log_mix(model.prior, K),
        _log_mix(model.process_noise),
        _log_mix(model.measurement_noise),
        K,
        "pcm",
        dims=dims,
    )
    mean_min, cov_min = jax.jit(jax.vmap(minimal, (0, None)))(zs, ts)
    filt = build_gsf(model, "ekf", PCM(max_components=K, capacity=K, dims=dims, newton_steps=0), capacity=K)
    info = jax.jit(jax.vmap(lambda z: run(filt, z, ts)[1]))(zs)
    return (np.asarray(a) for a in (mean_min, cov_min, info.mean, info.cov))


def test_minimal_pcm_gsf_equals_gmjax_1d():
    """The seed 000 jump system (the Table 7 PCM-GSF with the grid search), 6 runs of 60 steps."""
    mean_min, cov_min, mean_gm, cov_gm = _filter_runs(jump_system(n_steps=60), None, 6)
    assert np.abs(mean_min - mean_gm).max() < 1e-9
    assert np.abs(cov_min - cov_gm).max() < 1e-9


def test_minimal_pcm_gsf_equals_gmjax_4d():
    """The seed 000 Table 8 range-bearing system (clustering on position), 4 runs of 30 steps."""
    mean_min, cov_min, mean_gm, cov_gm = _filter_runs(range_bearing(duration=0.3), (0, 2), 4)
    assert np.abs(mean_min - mean_gm).max() < 1e-9
    assert np.abs(cov_min - cov_gm).max() < 1e-9 * max(1.0, np.abs(cov_gm).max())


def _row(system, filt, dtype, n_runs, repeats=None):
    row = {
        "system": system,
        "filter": filt,
        "dtype": dtype,
        "track_ise": False,
        "n_runs": n_runs,
        "gmjax_us_per_run_step": 2.0,
        "minimal_us_per_run_step": 1.0,
        "ratio": 2.0,
        "gmjax_compile_s": 1.0,
        "minimal_compile_s": 0.5,
        "max_abs_diff": 1e-12,
    }
    return row if repeats is None else {**row, "repeats": repeats}


def test_bench_merge_keeps_other_cases_their_runs_and_notes():
    """``--merge-with``: the rerun case replaces its rows, the kept rows keep their own run counts,
    and the table says each row's runs; the earlier notes survive a second merge."""
    from bench_gsf_kernel import merge_results, render_markdown

    first = {
        "rows": [_row("1-D", "NL-GSF", "float64", 1000), _row("1-D", "R-GSF", "float64", 200)],
        "note": "first run's note.",
        "loadavg_before": ["0.1", "0.2", "0.3"],
        "loadavg_after": ["1.1", "1.2", "1.3"],
    }
    rows, note, history = merge_results([_row("1-D", "R-GSF", "float64", 50, repeats=3)], first)
    assert [(r["filter"], r["n_runs"]) for r in rows] == [("NL-GSF", 1000), ("R-GSF", 50)]
    assert note == "Rows of 1 cases kept from an earlier run (load 0.1 0.2 0.3 / 1.1 1.2 1.3)."
    assert history == ["first run's note."]
    second = {**first, "rows": rows, "note": note, "history": history, "failed": []}
    md = render_markdown(second)
    assert "| 1-D | NL-GSF | float64 | off | 1000 |" in md
    assert "| 1-D | R-GSF | float64 | off | 50 |" in md
    assert "3 repeats, some rows' not recorded" in md
    assert f"Note: {note}" in md
    assert "## Earlier runs of the kept rows, newest first\n\n- first run's note.\n" in md
    _, _, carried = merge_results([], second)
    assert carried == [note, "first run's note."]
    # results written before the notes became a list carry them joined in one string
    legacy = {**second, "history": None, "previous_note": "older notes."}
    assert merge_results([], legacy)[2] == [note, "older notes."]
    assert "\n- older notes.\n" in render_markdown(legacy)


def test_time_alternating_times_one_call_of_each_per_round():
    """The benchmark's alternating rounds: every call compiled (first call) in order, then one call of
    each per round, so drift slows them alike; per call the best and median of its rounds."""
    from _common import time_alternating

    order: list[str] = []
    calls = [lambda name=name: order.append(name) for name in ("minimal", "grid", "newton")]
    timed = time_alternating(calls, repeats=3)
    assert order == ["minimal", "grid", "newton"] * 4
    assert len(timed) == 3
    for t in timed:
        assert set(t) == {"compile_s", "run_min_s", "run_median_s"}
        assert 0.0 <= t["run_min_s"] <= t["run_median_s"] and t["compile_s"] >= 0.0
