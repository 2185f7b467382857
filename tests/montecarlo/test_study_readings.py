"""The study readings of issue 19: R-GSF with a cost threshold (Xu et al. Fig. 10), the zero-centred glint
variant of Table 7, AGSSCKF with room to split, and why merge-based reducers give the same estimates."""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import studies
from gmjax.filters import run
from gmjax.mixture import GaussianMixture, moments
from gmjax.models import simulate
from gmjax.scenarios.gamma_system import gamma_system
from gmjax.scenarios.jump_system import jump_system


def test_r_gsf_threshold_lets_the_count_vary_and_caps_it_at_n_u():
    """Table 7's default R-GSF merges while Runnalls' cost < R_GSF_THRESHOLD (count varies, <= N_u = 20),
    R-GSF-20 merges to exactly 20, on the same simulated run."""
    study = studies.STUDIES["jump"]()
    sc = jump_system(n_steps=12)
    xs, zs, ts = simulate(sc, jax.random.key(0))
    counts = {}
    for name in ("R-GSF", "R-GSF-20"):
        filt = study.filters[name](sc)
        _, info = jax.jit(lambda z, f=filt: run(f, z, ts))(zs)
        counts[name] = np.asarray(info.n_components)
    assert counts["R-GSF-20"][2:].min() == 20  # 20 x 3 predicted components always merge down to 20
    assert counts["R-GSF"].max() <= 20 and counts["R-GSF"].min() < 20
    assert len(np.unique(counts["R-GSF"])) > 1  # the count changes over time (Fig. 10)


def test_zero_centred_glint_variant_is_its_own_table_and_keeps_the_variance():
    sc0, sc = jump_system(glint_location=0.0), jump_system()
    keys = jax.random.split(jax.random.key(1), 200_000)
    d0 = np.asarray(jax.vmap(lambda k: sc0.sample_process_noise(k, 1))(keys))[:, 0]
    d = np.asarray(jax.vmap(lambda k: sc.sample_process_noise(k, 1))(keys))[:, 0]
    q_mean, q_var = (float(np.asarray(a).squeeze()) for a in moments(sc.model.process_noise))
    se0 = d0.std() / np.sqrt(len(d0))
    assert abs(d0.mean()) < 4 * se0 and abs(d.mean() - q_mean) < 4 * se0  # centred at 0 vs at eq 50's mean
    np.testing.assert_allclose([d0.var(), d.var()], q_var, rtol=0.03)  # same spread: eq-50 variance
    np.testing.assert_allclose(d0 - d, -q_mean, atol=1e-9)  # same draws, shifted
    m0, v0 = (float(np.asarray(a).squeeze()) for a in moments(sc0.model.process_noise))
    assert abs(m0) < 1e-12 and v0 == pytest.approx(q_var, rel=1e-12)  # the filters' eq 50, translated
    np.testing.assert_allclose(sc0.model.process_noise.covs, sc.model.process_noise.covs)
    variant = studies.STUDIES["jump_zero_glint"]()
    assert variant.table == "seed000-table7-zero-glint" != studies.STUDIES["jump"]().table
    assert len({studies.STUDIES[n]().table for n in studies.STUDIES}) == len(studies.STUDIES)


def _split_room():
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from bench_seed001 import SPLIT_ROOM

    return SPLIT_ROOM


def test_agsckf_split_room_config_keeps_the_papers_n_max_as_posterior_slots():
    """45 working slots / q = 3 noise components = 15 posterior sub-filters (N_max = 15, §4), with room to
    split whenever Step 6 leaves fewer; the default keeps 15 // 3 = 5 and has no room after a prediction."""
    room = _split_room()
    q = len(gamma_system().model.process_noise.weights)
    assert q == 3 and room.capacity // q == 15 and room.n_max == room.capacity == 45


@pytest.mark.slow
def test_agsckf_split_room_keeps_n_max_posterior_components_and_splits_more_often():
    SPLIT_ROOM = _split_room()

    from gmjax.filters.agsf import AGSFConfig, build_agsf

    sc = gamma_system(n_steps=8, initial_update=True)
    sims = [simulate(sc, k) for k in jax.random.split(jax.random.key(2), 4)]
    zs, ts = jnp.stack([s[1] for s in sims]), sims[0][2]
    out = {}
    for name, cfg in (("default", AGSFConfig()), ("room", SPLIT_ROOM)):
        filt = build_agsf(sc.model, cfg)
        info = jax.jit(jax.vmap(lambda z, f=filt: run(f, z, ts)[1]))(zs)
        out[name] = (np.asarray(info.n_components), np.asarray(info.extra["n_split"]))
    assert out["default"][0].max() <= 15 // 3 and out["room"][0].max() <= 15
    assert out["room"][0].max() > 15 // 3
    assert (out["room"][1] > 0).mean() > (out["default"][1] > 0).mean()


@pytest.mark.parametrize("seed", [0, 1])
def test_merge_based_reducers_keep_the_mean_but_not_the_mixture(seed):
    """Why seed 003's GMRC and Runnalls tie on ARMSE: both merge by moments, so the reduced mixture's mean
    (the estimate, before or after reduction) is the same, while the mixtures -- and their ISE to the
    input -- differ (the setting that separates them)."""
    from gmjax.metrics import ise
    from gmjax.reduction import GMRC, Runnalls

    rng = np.random.default_rng(seed)
    n, d = 24, 3
    gm = GaussianMixture.create(
        rng.dirichlet(np.ones(n)),
        rng.normal(scale=3.0, size=(n, d)),
        np.stack([np.diag(rng.uniform(0.5, 2.0, d)) for _ in range(n)]),
    )
    red = {  # (compiled: eager, the reductions' ops compile one by one)
        name: jax.jit(lambda g, r=r: r(g)[0])(gm)
        for name, r in (("GMRC", GMRC(num_out=4, capacity=8)), ("Runnalls", Runnalls(num_out=4, capacity=8)))
    }
    m0, P0 = moments(gm)
    for g in red.values():
        m, P = moments(g)
        np.testing.assert_allclose(m, m0, atol=1e-10)
        np.testing.assert_allclose(P, P0, atol=1e-9)
    i_gmrc, i_run = (float(ise(gm, red[k])) for k in ("GMRC", "Runnalls"))
    assert abs(i_gmrc - i_run) > 1e-3 * max(i_gmrc, i_run)
