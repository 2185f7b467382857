"""Monte Carlo runner: chunk- and device-invariance, aggregation, errors."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

from gmjax import montecarlo
from gmjax.filters import build_ekf
from gmjax.filters.gsf import build_gsf
from gmjax.scenarios.jump_system import jump_system
from gmjax.reduction import PruneTop


def small_study(n_steps=10):
    sc = jump_system()._replace(n_steps=n_steps)
    return sc, build_gsf(sc.model, "ekf", PruneTop(num_out=4), capacity=4)


def test_same_numbers_for_any_chunk_size():
    sc, filt = small_study()
    a = montecarlo.monte_carlo(filt, sc, 7, jax.random.key(0), chunk_size=7, progress=False)
    b = montecarlo.monte_carlo(filt, sc, 7, jax.random.key(0), chunk_size=3, progress=False)
    for x, y in zip(jax.tree_util.tree_leaves(a.scores), jax.tree_util.tree_leaves(b.scores)):
        np.testing.assert_array_equal(x, y)
    assert a.armse == b.armse
    assert a.scores.sq_error.shape == (7, 10)


def test_same_numbers_on_four_forced_host_devices(tmp_path):
    sc, filt = small_study()
    ref = montecarlo.monte_carlo(filt, sc, 6, jax.random.key(5), chunk_size=4, progress=False)
    script = textwrap.dedent(
        f"""
        import jax, numpy as np
        jax.config.update("jax_enable_x64", True)
        assert len(jax.devices()) == 4, jax.devices()
        from gmjax import montecarlo
        from gmjax.filters.gsf import build_gsf
        from gmjax.scenarios.jump_system import jump_system
        from gmjax.reduction import PruneTop
        sc = jump_system()._replace(n_steps=10)
        filt = build_gsf(sc.model, "ekf", PruneTop(num_out=4), capacity=4)
        r = montecarlo.monte_carlo(filt, sc, 6, jax.random.key(5), chunk_size=4, progress=False)
        np.savez(r"{tmp_path / 'out.npz'}", sq=r.scores.sq_error, nees=r.scores.nees, n=r.scores.n_components)
        """
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    res = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    out = np.load(tmp_path / "out.npz")
    # Each device compiles a different per-device batch shape, so XLA may reassociate a sum:
    # equal to rounding (observed: <= 3e-14 relative), not necessarily bit for bit.
    np.testing.assert_allclose(out["sq"], ref.scores.sq_error, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(out["nees"], ref.scores.nees, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(out["n"], ref.scores.n_components)


def test_summary_matches_numpy_aggregation():
    sc, filt = small_study()
    r = montecarlo.monte_carlo(filt, sc, 5, jax.random.key(1), keep_trajectories=True, progress=False)
    err = r.scores.estimates - r.scores.truths
    rmse_t = np.sqrt((err**2).sum(-1).mean(0))
    np.testing.assert_allclose(r.rmse, rmse_t, rtol=1e-13)
    assert r.armse == pytest.approx(rmse_t.mean(), rel=1e-13)
    assert r.cep == pytest.approx(np.median(np.abs(err[..., 0])), rel=1e-13)
    assert r.anees == pytest.approx(r.scores.nees.mean(), rel=1e-13)
    assert r.median_nees == pytest.approx(np.median(r.scores.nees), rel=1e-13)
    assert r.armse_stderr > 0
    np.testing.assert_array_equal(r.n_components, r.scores.n_components.mean(0))
    assert r.compile_s > 0 and r.run_s > 0


def test_armse_stderr_matches_spread_of_independent_studies():
    # the delta-method standard error should describe the spread of ARMSE over independent studies:
    # one compiled study of 8 x 40 runs, summarised as 8 separate studies of 40 runs
    sc = jump_system()._replace(n_steps=10)
    big = montecarlo.monte_carlo(build_ekf(sc.model), sc, 320, jax.random.key(100), progress=False)
    armses, ses = [], []
    for g in range(8):
        part = jax.tree_util.tree_map(lambda a: a[g * 40 : (g + 1) * 40], big.scores)
        r = montecarlo.summarize(part, n_runs=40)
        armses.append(r.armse)
        ses.append(r.armse_stderr)
    spread = np.std(armses, ddof=1)
    # the sample std of 8 values is itself uncertain by ~25%: accept a factor-2 band
    assert 0.5 * np.mean(ses) < spread < 2.0 * np.mean(ses)


def test_single_gaussian_and_particle_filters_run_through_the_same_runner():
    from gmjax.filters import build_pf

    sc = jump_system()._replace(n_steps=8)
    for filt in (build_ekf(sc.model), build_pf(sc.model, 50)):
        r = montecarlo.monte_carlo(filt, sc, 3, jax.random.key(2), progress=False)
        assert r.rmse.shape == (8,)
        assert np.all(np.isfinite(r.rmse))


def test_bad_arguments_raise():
    sc, filt = small_study()
    with pytest.raises(ValueError, match="n_runs"):
        montecarlo.monte_carlo(filt, sc, 0, jax.random.key(0))
    with pytest.raises(ValueError, match="chunk_size"):
        montecarlo.monte_carlo(filt, sc, 2, jax.random.key(0), chunk_size=0)
