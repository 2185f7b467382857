"""Eager calls of ``run`` and ``simulate`` compile once per filter / scenario, and studies share a
scenario's simulation: same values as the traced paths, no second compile."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from gmjax import montecarlo
from gmjax._jitcache import IdentityCache
from gmjax.filters import base, build_ekf, build_pf, run
from gmjax.filters.gsf import build_gsf
from gmjax.models import base as models_base
from gmjax.models import simulate
from gmjax.reduction import PruneTop
from gmjax.scenarios.jump_system import jump_system


def test_identity_cache_compares_owners_by_identity_and_drops_the_least_recently_used():
    cache = IdentityCache(maxsize=2)
    a, b, equal_to_a = [1.0], [2.0], [1.0]
    assert cache.get((a,), lambda: "a") == "a"
    assert cache.get((a,), lambda: "again") == "a"  # the same object: a hit
    assert cache.get((equal_to_a,), lambda: "equal") == "equal"  # equal but another object: a miss
    assert cache.get((a,), lambda: "tagged", tag=(3, "x")) == "tagged"  # another tag: a miss
    assert len(cache) == 2  # (a,) untagged was the least recently used and went
    assert cache.get((a,), lambda: "remade") == "remade"  # (equal_to_a,) goes
    assert cache.get((a,), lambda: "no", tag=(3, "x")) == "tagged"
    assert cache.get((equal_to_a,), lambda: "equal again") == "equal again"
    assert cache.get((b, a), lambda: "pair") == "pair" and cache.get((b, a), lambda: "no") == "pair"


def _scan_of(filt):
    """The jitted scan ``run`` keeps for ``filt`` (``None`` if there is none)."""
    return base._EAGER_SCANS.get((filt,), lambda: None)


@pytest.mark.parametrize("kind", ["gsf", "pf"])
def test_eager_run_compiles_once_per_filter_and_equals_the_traced_run(kind):
    sc = jump_system()._replace(n_steps=12)
    if kind == "gsf":
        filt = build_gsf(sc.model, "ekf", PruneTop(num_out=5), capacity=5)  # the prior has 5
    else:
        filt = build_pf(sc.model, 64)
    traced = jax.jit(lambda z, k: run(filt, z, key=k)[1])
    for seed in (0, 1, 2):  # new measurements and keys, the same shapes
        _, zs, _ = simulate(sc, jax.random.key(seed))
        key = jax.random.key(10 + seed)
        info = run(filt, zs, key=key)[1]
        ref = traced(zs, key)
        np.testing.assert_allclose(info.mean, ref.mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(info.cov, ref.cov, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(info.n_components, ref.n_components)
    scan = _scan_of(filt)
    assert scan is not None and scan._cache_size() == 1  # three eager calls, one compiled program


def test_eager_run_still_validates_and_takes_a_prior_without_recompiling():
    sc = jump_system()._replace(n_steps=5)
    filt = build_ekf(sc.model)
    _, zs, _ = simulate(sc, jax.random.key(0))
    with pytest.raises(ValueError, match="zs"):
        run(filt, zs[:, None, :])
    prior = sc.model.prior
    moved = prior._replace(means=prior.means + 1.0)
    a, b = run(filt, zs, prior=prior)[1], run(filt, zs, prior=moved)[1]
    assert not np.allclose(a.mean, b.mean)
    ref = jax.jit(lambda z, p: run(filt, z, prior=p)[1])(zs, moved)
    np.testing.assert_allclose(b.mean, ref.mean, rtol=1e-12, atol=1e-12)
    noise = filt.params.measurement_noise
    louder = filt.params._replace(measurement_noise=noise._replace(covs=4.0 * noise.covs))
    c = run(filt, zs, params=louder)[1]
    assert np.all(c.cov[-1] > a.cov[-1])  # a noisier sensor leaves more uncertainty
    ref = jax.jit(lambda z, p: run(filt, z, params=p)[1])(zs, louder)
    np.testing.assert_allclose(c.cov, ref.cov, rtol=1e-12, atol=1e-14)
    assert _scan_of(filt)._cache_size() == 1  # priors and params are arguments of one program


def test_eager_simulate_compiles_once_per_scenario_and_equals_the_traced_simulation():
    sc = jump_system()._replace(n_steps=9)
    keys = jax.random.split(jax.random.key(4), 3)
    xs, zs, ts = jax.vmap(lambda k: simulate(sc, k))(keys)  # traced, batched (rounds differently)
    for i in range(3):
        xi, zi, ti = simulate(sc, keys[i])  # eager
        np.testing.assert_allclose(xi, xs[i], rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(zi, zs[i], rtol=1e-13, atol=1e-13)
        np.testing.assert_array_equal(ti, ts[i])
    program = models_base._EAGER_SIMULATIONS.get((sc,), lambda: None)
    assert program is not None and program._cache_size() == 1


def test_filters_of_one_scenario_share_its_compiled_simulation():
    sc = jump_system()._replace(n_steps=6)
    key = jax.random.key(5)
    kw = dict(chunk_size=2, keep_trajectories=True, progress=False)
    a = montecarlo.monte_carlo(build_ekf(sc.model), sc, 4, key, **kw)
    b = montecarlo.monte_carlo(build_gsf(sc.model, "ekf", PruneTop(num_out=5), capacity=5), sc, 4, key, **kw)
    np.testing.assert_array_equal(a.scores.truths, b.scores.truths)
    mesh = jax.sharding.Mesh(np.asarray(jax.devices()), ("runs",))
    program = montecarlo.driver._simulation_program(sc, 2, mesh)
    assert len(program._compiled) == 1  # compiled for the first study, reused by the second
    # the same runs as the differentiable path, which simulates inside its one program
    ref = montecarlo.study_scores(build_ekf(sc.model), sc, 4, key)
    np.testing.assert_allclose(a.scores.sq_error, ref.sq_error, rtol=1e-12, atol=1e-14)
