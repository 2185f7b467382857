"""Monte Carlo runner: streaming accumulators, chunking, split/merge, resume, devices, hosts, gradients."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import montecarlo
from gmjax.filters import build_ekf
from gmjax.filters.gsf import build_gsf
from gmjax.reduction import PruneTop
from gmjax.scenarios.jump_system import jump_system

ROOT = Path(__file__).resolve().parents[2]
MEDIAN_REL = (
    10 ** (1 / montecarlo.accumulate.HIST_BINS_PER_DECADE) - 1
)  # the histogram median's stated accuracy

SMALL = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)
    from gmjax import montecarlo
    from gmjax.filters.gsf import build_gsf
    from gmjax.scenarios.jump_system import jump_system
    from gmjax.reduction import PruneTop
    sc = jump_system()._replace(n_steps=10)
    filt = build_gsf(sc.model, "ekf", PruneTop(num_out=4), capacity=5)
    """
)


def small_study(n_steps=10):
    sc = jump_system()._replace(n_steps=n_steps)
    return sc, build_gsf(sc.model, "ekf", PruneTop(num_out=4), capacity=5)


def numbers(r: montecarlo.MonteCarloResult) -> dict:
    """Every number of a result (not the timings)."""
    out = {
        k: getattr(r, k)
        for k in (
            "rmse",
            "position_rmse",
            "armse",
            "armse_stderr",
            "position_armse",
            "position_armse_stderr",
            "nees",
            "anees",
            "median_nees",
            "cep",
            "mean_cost",
            "mean_ise",
            "n_components",
            "flag_rate",
            "n_runs_flagged",
            "n_runs",
        )
    }
    out.update({f"moments.{k}": v for k, v in r.moments._asdict().items()})
    return out


def assert_bit_identical(a, b):
    na, nb = numbers(a), numbers(b)
    for k in na:
        np.testing.assert_array_equal(na[k], nb[k], err_msg=k)


def assert_close(a, b, rtol):
    na, nb = numbers(a), numbers(b)
    for k in na:
        if k.startswith("moments.hist") or k in ("median_nees", "cep"):
            continue  # bin edges may fall differently by one ulp
        np.testing.assert_allclose(na[k], nb[k], rtol=rtol, atol=1e-12, err_msg=k)


def test_run_keys_are_the_split_keys():
    key = jax.random.key(11)
    split = jax.random.key_data(jax.random.split(key, 50))
    folded = jax.random.key_data(
        jax.vmap(montecarlo.run_key, (None, 0))(key, jnp.arange(50, dtype=jnp.uint32))
    )
    np.testing.assert_array_equal(split, folded)


def test_summary_matches_numpy_aggregation_of_every_run():
    sc, filt = small_study()
    r = montecarlo.monte_carlo(
        filt, sc, 13, jax.random.key(1), chunk_size=4, keep_trajectories=True, progress=False
    )
    s = r.scores
    assert s.sq_error.shape == (13, 10) and s.estimates.shape == (13, 10, 1)
    err = s.estimates - s.truths
    rmse_t = np.sqrt((err**2).sum(-1).mean(0))
    np.testing.assert_allclose(r.rmse, rmse_t, rtol=1e-13)
    assert r.armse == pytest.approx(rmse_t.mean(), rel=1e-13)
    # delta-method standard error computed from every run (the 0.1 formula)
    per_run = (s.sq_error / (2 * 10 * rmse_t)).sum(1)
    assert r.armse_stderr == pytest.approx(per_run.std(ddof=1) / np.sqrt(13), rel=1e-10)
    assert r.anees == pytest.approx(s.nees.mean(), rel=1e-13)
    np.testing.assert_allclose(r.nees, s.nees.mean(0), rtol=1e-13)
    assert r.median_nees == pytest.approx(np.median(s.nees), rel=MEDIAN_REL)
    assert r.cep == pytest.approx(np.median(np.abs(err[..., 0])), rel=MEDIAN_REL)
    np.testing.assert_allclose(r.n_components, s.n_components.mean(0), rtol=1e-13)
    assert r.flag_rate == pytest.approx(s.flags.mean())
    assert r.n_runs_flagged == int(s.flags.any(1).sum())
    assert r.compile_s > 0 and r.run_s > 0 and r.n_runs == 13 and r.runs == (0, 13)


def test_histogram_median_is_within_its_stated_accuracy():
    rng = np.random.default_rng(0)
    for n in (1, 2, 7, 1000):
        x = np.exp(rng.normal(0, 5, size=(n, 3)))
        s = montecarlo.RunScores(x, x**2, x, x, np.zeros(x.shape, bool))
        r = montecarlo.summarize(s)
        assert r.median_nees == pytest.approx(np.median(x), rel=MEDIAN_REL)
        assert r.cep == pytest.approx(np.median(x), rel=MEDIAN_REL)
    with_nan = montecarlo.summarize(
        montecarlo.RunScores(*(np.asarray([[1.0, np.nan]]),) * 4, np.zeros((1, 2), bool))
    )
    assert np.isnan(with_nan.median_nees)


def assert_same_study(merged, whole):
    """Every number and every accumulator bit for bit, and the block sums' nodes."""
    assert_bit_identical(merged, whole)
    assert merged.runs == whole.runs and merged.n_runs == whole.n_runs
    assert len(merged.sums.nodes) == len(whole.sums.nodes)
    for (la, ia, ma), (lb, ib, mb) in zip(merged.sums.nodes, whole.sums.nodes):
        assert (la, ia) == (lb, ib)
        for x, y in zip(ma, mb):
            np.testing.assert_array_equal(x, y)


def test_splits_at_block_boundaries_merge_bit_identical_to_the_whole_study():
    """Issue 48 item 1: 2 and 3 parts, in any order, give every field of the whole study bit for bit."""
    sc, filt = small_study()
    key = jax.random.key(0)
    study = lambda runs, keep: montecarlo.monte_carlo(  # noqa: E731
        filt, sc, 23, key, chunk_size=3, runs=runs, keep_runs=keep, progress=False
    )
    whole = study(range(23), 23)
    assert whole.sums.block_size == 3 and whole.sums.n_blocks == 8 and len(whole.sums.nodes) == 1
    for bounds in ((0, 6, 23), (0, 9, 15, 23), (0, 3, 21, 23)):
        parts = [study(range(a, b), b - a) for a, b in zip(bounds, bounds[1:])]
        # per-run numbers: the same compiled chunk, so bit for bit
        for x, *ys in zip(whole.scores, *(p.scores for p in parts)):
            if x is not None:
                np.testing.assert_array_equal(x, np.concatenate(ys))
        for order in (parts, parts[::-1]):
            assert_same_study(montecarlo.merge(order), whole)
    # the merge of a merge is the same study too, and a part's own numbers are its runs'
    a, b, c = (study(range(x, y), 0) for x, y in ((0, 9), (9, 15), (15, 23)))
    assert_same_study(montecarlo.merge([montecarlo.merge([b, c]), a]), whole)
    assert b.n_runs == 6 and b.runs == (9, 15)
    np.testing.assert_allclose(b.rmse, np.sqrt(whole.scores.sq_error[9:15].mean(0)), rtol=1e-13)


def test_merge_refuses_what_is_not_one_study():
    """Issue 48 item 2: gaps, overlaps, other block sizes, keys, filters, scenarios, dtypes, versions."""
    sc, filt = small_study()
    key = jax.random.key(0)
    part = lambda runs, **kw: montecarlo.monte_carlo(  # noqa: E731
        kw.pop("filt", filt),
        kw.pop("sc", sc),
        20,
        kw.pop("key", key),
        runs=runs,
        chunk_size=kw.pop("chunk_size", 5),
        progress=False,
    )
    a, c = part(range(0, 5)), part(range(10, 20))
    with pytest.raises(ValueError, match=r"runs 5..9 are missing .* run runs=range\(5, 10\)"):
        montecarlo.merge([a, c])
    with pytest.raises(ValueError, match="overlap"):
        montecarlo.merge([a, a])
    with pytest.raises(
        ValueError, match=r"sums that do not combine exactly .block_size differs: 5 in \(0, 10\) vs 10"
    ):
        montecarlo.merge([part(range(0, 10)), part(range(10, 20), chunk_size=10)])
    cases = (
        (part(range(5, 20), key=jax.random.key(1)), "different studies .key differs"),
        (
            part(
                range(5, 20),
                filt=filt._replace(
                    params=jax.tree_util.tree_map(
                        lambda x: x * 2 if jnp.issubdtype(x.dtype, jnp.floating) else x, filt.params
                    )
                ),
            ),
            "different studies .filter differs",
        ),
        (part(range(5, 20), sc=sc._replace(name="other")), "different studies .scenario differs"),
    )
    for other, match in cases:
        with pytest.raises(ValueError, match=match):
            montecarlo.merge([a, other])
    b = part(range(5, 20))
    assert montecarlo.merge([a, b]).n_runs == 20
    newer = b._replace(config=dict(b.config, gmjax_version="9.9"))
    with pytest.raises(ValueError, match="gmjax_version differs.*exact=False"):
        montecarlo.merge([a, newer])
    assert montecarlo.merge([a, newer], exact=False).config["exact"] is False
    f32 = b._replace(config=dict(b.config, dtype="float32"))
    with pytest.raises(ValueError, match="dtype differs"):
        montecarlo.merge([a, f32], exact=False)
    # a result without block sums (summarize) merges only to rounding, when asked
    whole = part(range(20))
    scores = jax.jit(lambda k: montecarlo.study_scores(filt, sc, 20, k))(key)
    first5 = jax.tree_util.tree_map(lambda x: x[:5], scores)
    s = montecarlo.summarize(first5)
    with pytest.raises(ValueError, match="no block sums"):
        montecarlo.merge([s._replace(config=a.config), b])
    loose = montecarlo.merge([s._replace(config=a.config), b], exact=False)
    assert loose.armse == pytest.approx(whole.armse, rel=1e-12)


def test_runs_off_the_block_grid_are_refused():
    sc, filt = small_study()
    with pytest.raises(ValueError, match=r"off the study's block grid .blocks of 5 runs.*range\(5, 15\)"):
        montecarlo.monte_carlo(
            filt, sc, 20, jax.random.key(0), chunk_size=5, runs=range(7, 15), progress=False
        )
    with pytest.raises(ValueError, match="off the study's block grid"):
        montecarlo.monte_carlo(
            filt, sc, 20, jax.random.key(0), chunk_size=5, runs=range(5, 12), progress=False
        )
    # stop = n_runs is always on the grid; the default chunk makes round splits fall on it
    assert [montecarlo.default_chunk_size(n) for n in (1, 20, 100, 499, 1000, 10**4, 10**6)] == [
        1,
        2,
        10,
        50,
        100,
        1000,
        1000,
    ]


def test_chunk_sizes_agree_to_rounding():
    """Issue 15 item 5: different chunk sizes compile different batch shapes (module docstring)."""
    sc, filt = small_study()
    a = montecarlo.monte_carlo(filt, sc, 7, jax.random.key(0), chunk_size=7, keep_runs=7, progress=False)
    b = montecarlo.monte_carlo(filt, sc, 7, jax.random.key(0), chunk_size=3, keep_runs=7, progress=False)
    for x, y in zip(a.scores, b.scores):
        if x is not None:
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-14)
    assert_close(a, b, rtol=1e-12)


def test_save_load_round_trip_and_strict_json(tmp_path):
    sc, filt = small_study(n_steps=4)
    r = montecarlo.monte_carlo(filt, sc, 1, jax.random.key(3), keep_runs=1, progress=False)
    assert np.isnan(r.armse_stderr)  # one run: undefined, and JSON says null
    text = json.dumps(r.to_json(), allow_nan=False)
    assert json.loads(text)["armse_stderr"] is None
    cfg = r.config
    assert cfg["dtype"] == "float64" and cfg["n_runs"] == 1 and cfg["key"]["data"] and cfg["jax_version"]
    r.save(tmp_path / "r.npz")
    back = montecarlo.load_result(tmp_path / "r.npz")
    assert_bit_identical(r, back)
    np.testing.assert_array_equal(back.scores.sq_error, r.scores.sq_error)
    assert back.config == json.loads(json.dumps(cfg))


def test_checkpoint_resumes_bit_identical_after_a_kill(tmp_path):
    """Kill a study (SIGKILL) after its second checkpoint, rerun the same call: bit-identical result."""
    ckpt = tmp_path / "study.npz"
    call = (
        "montecarlo.monte_carlo(filt, sc, 14, jax.random.key(9), chunk_size=3, keep_runs=5, "
        f"checkpoint=r'{ckpt}', progress=False)"
    )
    script = SMALL + textwrap.dedent(
        f"""
        import os, signal
        writes = []
        original = montecarlo.driver._write_checkpoint
        def write_then_die(*args, **kwargs):
            original(*args, **kwargs)
            writes.append(1)
            if len(writes) == 2:
                os.kill(os.getpid(), signal.SIGKILL)
        montecarlo.driver._write_checkpoint = write_then_die
        {call}
        """
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    res = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert res.returncode == -9, res.stderr[-2000:]
    with np.load(ckpt) as f:
        assert int(f["next_run"]) == 6  # two chunks of 3 done, the study killed mid-way
    sc, filt = small_study()
    stale = tmp_path / "study.npz.tmp-999999.npz"  # what a kill during a write leaves behind
    stale.write_bytes(b"PK\x03\x04 half a zip")
    resumed = eval(call, {"montecarlo": montecarlo, "filt": filt, "sc": sc, "jax": jax})
    assert resumed.resumed_runs == 6
    assert sorted(p.name for p in tmp_path.iterdir()) == ["study.npz"]  # no temporary file left
    fresh = montecarlo.monte_carlo(filt, sc, 14, jax.random.key(9), chunk_size=3, keep_runs=5, progress=False)
    assert_bit_identical(resumed, fresh)
    for x, y in zip(resumed.scores, fresh.scores):
        if x is not None:
            np.testing.assert_array_equal(x, y)
    # a finished checkpoint returns the same result without running anything
    again = eval(call, {"montecarlo": montecarlo, "filt": filt, "sc": sc, "jax": jax})
    assert again.resumed_runs == 14
    assert_bit_identical(again, fresh)
    # another configuration is refused, naming what differs
    with pytest.raises(ValueError, match="checkpoint.*differs in: block_size.*resume=False"):
        montecarlo.monte_carlo(
            filt, sc, 14, jax.random.key(9), chunk_size=4, keep_runs=5, checkpoint=ckpt, progress=False
        )
    with pytest.raises(ValueError, match="checkpoint.*differs in: key"):
        montecarlo.monte_carlo(
            filt, sc, 14, jax.random.key(8), chunk_size=3, keep_runs=5, checkpoint=ckpt, progress=False
        )


def test_broken_checkpoints_are_refused_naming_the_file_and_the_remedy(tmp_path):
    """Issue 48 item 3: truncated, empty, bit-flipped, foreign and other-version checkpoints."""
    sc, filt = small_study(n_steps=4)
    key = jax.random.key(2)
    ckpt = tmp_path / "c.npz"
    study = lambda **kw: montecarlo.monte_carlo(  # noqa: E731
        filt, sc, 6, key, chunk_size=2, checkpoint=ckpt, progress=False, **kw
    )
    good = study()
    data = ckpt.read_bytes()
    arrays = dict(np.load(ckpt))
    cases = {  # what the file holds: the cause the message gives
        "truncated": (data[: len(data) // 2], "is truncated or corrupt"),
        "empty": (b"", "is empty"),
        "not npz": (b"hello", "is truncated or corrupt"),
    }
    for content, match in cases.values():
        ckpt.write_bytes(content)
        with pytest.raises(ValueError, match=f"checkpoint: '{ckpt}' {match}.*resume=False"):
            study()
    flipped = dict(arrays)
    flipped["moments.mean"] = arrays["moments.mean"].copy()
    flipped["moments.mean"].flat[3] = np.nextafter(flipped["moments.mean"].flat[3], np.inf)
    with open(ckpt, "wb") as f:
        np.savez(f, **flipped)  # one bit changed, the old checksum kept
    with pytest.raises(ValueError, match="is corrupt: its contents do not match the checksum.*resume=False"):
        study()
    cfg = json.loads(str(arrays["config"]))
    montecarlo._files._write_npz(
        ckpt, dict(arrays, config=np.asarray(json.dumps(dict(cfg, gmjax_version="9.9.9"))))
    )
    with pytest.raises(ValueError, match="written by gmjax 9.9.9, this is gmjax .*resume=False"):
        study()
    old = {k: v for k, v in arrays.items() if k != "checksum"}
    with open(ckpt, "wb") as f:
        np.savez(f, **old)
    with pytest.raises(ValueError, match="written by an older gmjax"):
        study()
    np.savez(ckpt, x=np.zeros(2))
    with pytest.raises(ValueError, match="is not a gmjax Monte Carlo checkpoint file"):
        study()
    again = study(resume=False)  # starts again and overwrites the broken file
    assert again.resumed_runs == 0
    assert_bit_identical(again, good)
    assert study().resumed_runs == 6
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.npz"]
    # a saved result is checked the same way
    good.save(tmp_path / "r.npz")
    (tmp_path / "r.npz").write_bytes((tmp_path / "r.npz").read_bytes()[:100])
    with pytest.raises(ValueError, match="result: .*r.npz' is truncated or corrupt"):
        montecarlo.load_result(tmp_path / "r.npz")


def test_progress_announces_compilation_and_moves_ten_times(capsys):
    sc, filt = small_study(n_steps=4)
    montecarlo.monte_carlo(filt, sc, 20, jax.random.key(0), progress=True)
    err = capsys.readouterr().err
    assert "compiling" in err and " s\n" in err
    bars = [ln for ln in err.replace("\r", "\n").splitlines() if "runs/s" in ln]
    assert len(bars) >= 10 and "20/20 runs" in bars[-1] and "ETA" in bars[-1]
    montecarlo.monte_carlo(filt, sc, 3, jax.random.key(0), progress=False)
    assert capsys.readouterr().err == ""


def test_flags_reduce_every_flag_field():
    from typing import NamedTuple

    class Flags(NamedTuple):  # e.g. with a fourth, new flag
        a: jax.Array
        b: jax.Array
        c: jax.Array
        nonfinite: jax.Array

    f = jnp.zeros(5, bool)
    flags = Flags(f, f, f, f.at[3].set(True))
    np.testing.assert_array_equal(montecarlo.runs._any_flag(flags), f.at[3].set(True))
    s = montecarlo.RunScores(
        *(np.ones((2, 5)),) * 4, np.stack([np.zeros(5, bool), np.asarray(flags.nonfinite)])
    )
    r = montecarlo.summarize(s)
    assert r.n_runs_flagged == 1 and r.flag_rate == pytest.approx(0.1)


def test_armse_stderr_matches_spread_of_independent_studies():
    # the delta-method standard error should describe the spread of ARMSE over independent studies:
    # one compiled study of 8 x 40 runs, summarised as 8 separate studies of 40 runs
    sc = jump_system()._replace(n_steps=10)
    big = montecarlo.monte_carlo(
        build_ekf(sc.model), sc, 320, jax.random.key(100), chunk_size=64, keep_runs=320, progress=False
    )
    parts = [
        montecarlo.summarize(jax.tree_util.tree_map(lambda a: a[g * 40 : (g + 1) * 40], big.scores))
        for g in range(8)
    ]
    spread = np.std([p.armse for p in parts], ddof=1)
    se = np.mean([p.armse_stderr for p in parts])
    # the sample std of 8 values is itself uncertain by ~25%: accept a factor-2 band
    assert 0.5 * se < spread < 2.0 * se
    # the parts merge into the whole study
    assert montecarlo.merge(
        [p._replace(runs=(40 * g, 40 * (g + 1))) for g, p in enumerate(parts)], exact=False
    ).armse == pytest.approx(big.armse, rel=1e-13)


def test_single_gaussian_and_particle_filters_run_through_the_same_runner():
    from gmjax.filters import build_pf

    sc = jump_system()._replace(n_steps=8)
    for filt in (build_ekf(sc.model), build_pf(sc.model, 50)):
        r = montecarlo.monte_carlo(filt, sc, 3, jax.random.key(2), progress=False)
        assert r.rmse.shape == (8,)
        assert np.all(np.isfinite(r.rmse))


def test_study_loss_gradient_matches_finite_differences():
    """``jax.grad`` of a study's ARMSE w.r.t. a noise variance in ``filter.params`` (central differences)."""
    sc, filt = small_study(n_steps=6)
    q = filt.params.model.process_noise

    def params_at(scale):
        return filt.params._replace(
            model=filt.params.model._replace(process_noise=q._replace(covs=q.covs * scale))
        )

    f = jax.jit(
        lambda s: montecarlo.study_loss(
            filt, sc, 4, jax.random.key(5), montecarlo.armse_loss(), params=params_at(s)
        )
    )
    g = float(jax.grad(f)(1.3))
    h = 1e-6
    fd = (float(f(1.3 + h)) - float(f(1.3 - h))) / (2 * h)
    assert abs(g) > 1e-6
    assert g == pytest.approx(fd, rel=1e-5)
    # the same runs as monte_carlo
    r = montecarlo.monte_carlo(filt._replace(params=params_at(1.3)), sc, 4, jax.random.key(5), progress=False)
    assert r.position_armse == pytest.approx(float(f(1.3)), rel=1e-12)


def test_bad_arguments_raise():
    sc, filt = small_study()
    key = jax.random.key(0)
    for kwargs, match in (
        ({"n_runs": 0}, "n_runs"),
        ({"chunk_size": 0}, "chunk_size"),
        ({"runs": range(0, 9)}, "runs"),
        ({"runs": range(2, 2)}, "runs"),
        ({"keep_runs": -1}, "keep_runs"),
    ):
        args = {"n_runs": 2, **kwargs}
        with pytest.raises(ValueError, match=match):
            montecarlo.monte_carlo(filt, sc, args.pop("n_runs"), key, progress=False, **args)
    with pytest.raises(ValueError, match="n_steps"):
        montecarlo.monte_carlo(filt, sc._replace(n_steps=0), 2, key, progress=False)
    for bad in (0, 1.5, "seed", jax.random.split(key, 2)):
        with pytest.raises(ValueError, match=r"key: expected (a|one) PRNG key"):
            montecarlo.monte_carlo(filt, sc, 2, bad, progress=False)
    legacy = montecarlo.monte_carlo(filt, sc, 2, jax.random.key_data(key), progress=False)  # raw uint32 data
    assert legacy.config["key"] == montecarlo.monte_carlo(filt, sc, 2, key, progress=False).config["key"]
    too_small = build_gsf(sc.model, "ekf", PruneTop(num_out=4), capacity=4)  # the prior has 5
    with pytest.raises(ValueError, match="prior: 5 live components exceed the filter capacity 4"):
        montecarlo.monte_carlo(too_small, sc, 2, key, progress=False)
    sc32 = jump_system(n_steps=5, dtype=jnp.float32)
    with pytest.raises(ValueError, match="filter: its params hold.*float64"):
        montecarlo.monte_carlo(filt, sc32, 2, key, progress=False)
    filt32 = build_gsf(sc32.model, "ekf", PruneTop(num_out=4), capacity=5)
    r32 = montecarlo.monte_carlo(filt32, sc32, 2, key, progress=False)  # float32 under x64 stays float32
    assert r32.config["dtype"] == "float32" and np.isfinite(r32.armse)
    promotes = sc32._replace(sample_process_noise=lambda key, t: jnp.zeros(1, jnp.float64))
    with pytest.raises(ValueError, match="scenario: 'jump' .float32. cannot be simulated"):
        montecarlo.monte_carlo(filt32, promotes, 2, key, progress=False)


def test_same_bits_on_four_forced_host_devices(tmp_path):
    """Four devices, chunks of 8 (blocks of 2 runs) against one device with chunks of 2: the same blocks,
    so the same bits, and parts run on either merge into the whole."""
    sc, filt = small_study()
    ref = montecarlo.monte_carlo(filt, sc, 11, jax.random.key(5), chunk_size=2, keep_runs=11, progress=False)
    montecarlo.monte_carlo(
        filt, sc, 11, jax.random.key(5), chunk_size=2, keep_runs=11, runs=range(0, 4), progress=False
    ).save(tmp_path / "part0.npz")
    script = SMALL + textwrap.dedent(
        f"""
        assert len(jax.devices()) == 4, jax.devices()
        r = montecarlo.monte_carlo(filt, sc, 11, jax.random.key(5), chunk_size=8, keep_runs=11, progress=False)
        r.save(r"{tmp_path / "out.npz"}")
        r = montecarlo.monte_carlo(filt, sc, 11, jax.random.key(5), chunk_size=8, keep_runs=11,
                                   runs=range(4, 11), progress=False)
        r.save(r"{tmp_path / "part1.npz"}")
        """
    )
    env = dict(  # the parent's flags (conftest.py's optimisation level) plus four host devices
        os.environ,
        XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip(),
        JAX_PLATFORMS="cpu",
        PYTHONPATH=str(ROOT),
    )
    res = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    out = montecarlo.load_result(tmp_path / "out.npz")
    assert out.config["devices"]["count"] == 4 and out.config["block_size"] == 2
    np.testing.assert_array_equal(out.scores.sq_error, ref.scores.sq_error)
    assert_same_study(out, ref)
    parts = [montecarlo.load_result(tmp_path / f"part{i}.npz") for i in (0, 1)]
    assert_same_study(montecarlo.merge(parts), ref)  # one part on one device, the other on four


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_with_jax_distributed_equal_one_process(tmp_path):
    """Issue 48 item 6: two CPU processes under ``jax.distributed`` (gloo collectives), one device each,
    chunks of 4 (blocks of 2), return the bits of one process with chunks of 2."""
    sc, filt = small_study()
    ref = montecarlo.monte_carlo(filt, sc, 11, jax.random.key(4), chunk_size=2, keep_runs=5, progress=False)
    port = _free_port()
    script = (
        textwrap.dedent(
            """
        import sys, jax
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        pid = int(sys.argv[1])
        jax.distributed.initialize(coordinator_address=sys.argv[2], num_processes=2, process_id=pid)
        """
        )
        + SMALL
        + textwrap.dedent(
            """
        assert jax.process_count() == 2 and len(jax.devices()) == 2, jax.devices()
        r = montecarlo.monte_carlo(filt, sc, 11, jax.random.key(4), chunk_size=4, keep_runs=5, progress=False)
        r.save(sys.argv[3] + f"/out{pid}.npz")
        """
        )
    )
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
    # compiled as the parent compiles (conftest.py's flags), without any forced device count
    env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split() if "device_count" not in f)
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", script, str(i), f"127.0.0.1:{port}", str(tmp_path)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in (0, 1)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (_, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    r0 = montecarlo.load_result(tmp_path / "out0.npz")
    r1 = montecarlo.load_result(tmp_path / "out1.npz")
    assert_bit_identical(r0, r1)  # every process holds the same all-reduced accumulators
    assert r0.config["devices"] == {"count": 2, "platform": "cpu", "processes": 2}
    np.testing.assert_array_equal(r0.scores.sq_error, ref.scores.sq_error)
    assert_same_study(r0, ref)


def test_study_of_an_irregular_time_scenario_uses_its_inputs():
    """A scenario with per-step inputs (irregular dt) runs through monte_carlo, with the filter fed the
    same StepInputs as filters.run on the simulated run."""
    from gmjax import mixture
    from gmjax.filters import build_kf
    from gmjax.filters.base import StepInputs, run
    from gmjax.models import inputs_from_times, scenario_from_model, simulate
    from gmjax.models import library as lib

    model = lib.state_space_model(
        lib.constant_velocity(1, 0.5),
        lib.cartesian_position((0,), 2, 0.1),
        mixture.from_gaussian(jnp.zeros(2), jnp.eye(2)),
    )
    sc = scenario_from_model(model, 6, inputs=inputs_from_times(np.array([0.1, 0.3, 1.3, 1.4, 2.9, 3.0])))
    filt = build_kf(model)
    key = jax.random.key(3)
    res = montecarlo.monte_carlo(filt, sc, 4, key, keep_runs=4, progress=False)
    k_sim, k_filt = jax.random.split(montecarlo.run_key(key, 2))
    xs, zs, steps = simulate(sc, k_sim)
    assert isinstance(steps, StepInputs)
    _, infos = run(filt, zs, steps, key=k_filt)
    np.testing.assert_allclose(res.scores.sq_error[2], ((infos.mean - xs[1:]) ** 2).sum(-1), rtol=1e-12)


def test_readme_monte_carlo_block_runs_as_written(tmp_path, monkeypatch):
    """Issue 48 item 4: the README's "Monte Carlo studies at scale" block, gradient line included."""
    import re

    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Monte Carlo studies at scale") :]
    source = re.search(r"```python\n(.*?)```", section, flags=re.S).group(1)
    assert "gmjax.grad(" in source and "merge(" in source and "checkpoint=" in source
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(source, "README.md", "exec"), ns)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["study.npz", "study_result.npz"]
    assert_same_study(ns["merged"], ns["r"])
    g = ns["grads"]
    assert g.model.measurement_noise.mask is None and np.all(np.isfinite(g.model.measurement_noise.covs))
    assert float(jnp.abs(g.model.measurement_noise.covs).sum()) > 0
