"""The API boundary's answers to the fuzz residue of issue 48 item 5: each input is cast where the
intent is unambiguous, otherwise refused with a ValueError naming the argument.

- a float32 model run on float64 measurements (or float64 times) under x64: the measurements follow the
  model's dtype (before, the KF, GSF and PF failed with a ``lax.scan`` carry TypeError), and the result
  equals the run on float32 measurements bit for bit;
- ``monte_carlo(..., key=0)``: refused naming ``key``;
- ``GaussianMixture.create`` with capacity 2.5, a complex mean or ``d = 0``: refused naming the field;
- a GM-PHD scan cut by the caller: :func:`gmjax.multitarget.pad_scans` pads and flags it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import filters, reduction
from gmjax import multitarget as mt
from gmjax.mixture import GaussianMixture
from gmjax.montecarlo import monte_carlo
from gmjax.scenarios.jump_system import jump_system

F32 = jnp.float32


def _float32_filters():
    scenario = jump_system(n_steps=6, dtype=F32)
    one = jnp.ones((1, 1), F32)
    kf = filters.kalman_filter(one, one, one, one, jnp.zeros(1, F32), one)
    gsf = filters.build_gsf(scenario.model, "ekf", reduction.PruneTop(num_out=4), capacity=5)
    pf = filters.build_pf(scenario.model, 64)
    rpf = filters.build_pf(scenario.model, 64, regularized=True)
    return {"kf": kf, "gsf": gsf, "pf": pf, "rpf": rpf}


@pytest.mark.parametrize("name", ["kf", "gsf", "pf", "rpf"])
@pytest.mark.parametrize("jit", [False, True])
def test_float32_model_on_float64_measurements_runs_in_float32(name, jit):
    filt = _float32_filters()[name]
    zs64 = np.random.default_rng(1).normal(size=(6, 1))
    times64 = jnp.arange(1.0, 7.0, dtype=jnp.float64)
    key = jax.random.key(3)

    def go(zs, times):
        return filters.run(filt, zs, times, key=key)

    go = jax.jit(go) if jit else go
    states64, infos64 = go(jnp.asarray(zs64), times64)
    states32, infos32 = go(jnp.asarray(zs64, F32), times64.astype(F32))
    for a, b in zip(
        jax.tree_util.tree_leaves((states64, infos64)), jax.tree_util.tree_leaves((states32, infos32))
    ):
        assert a.dtype == b.dtype
        if jnp.issubdtype(a.dtype, jnp.floating):
            assert a.dtype == F32
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.isfinite(np.asarray(infos64.loglik)).all()


@pytest.mark.parametrize("key", [0, 1.5, "seed", np.zeros(3, np.uint32)])
def test_monte_carlo_refuses_a_key_that_is_not_a_prng_key(key):
    scenario = jump_system(n_steps=3)
    with pytest.raises(ValueError, match=r"^key: "):
        monte_carlo(filters.build_ekf(scenario.model), scenario, 4, key)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"capacity": 2.5}, r"^capacity: expected a whole number of slots \(an int\), got 2.5"),
        ({"capacity": True}, r"^capacity: "),
        ({"capacity": 1}, r"^capacity: 1 is smaller than the number of components 2"),
        ({"means": np.zeros((2, 1)) + 1j}, r"^means: expected real numbers, got a complex array"),
        ({"weights": np.array([True, True])}, r"^weights: expected real numbers, got a boolean array"),
        ({"covs": np.array(["a", "b"])}, r"^covs: expected real numbers, got a non-numeric array"),
        ({"means": np.zeros((2, 0)), "covs": np.ones((2, 0, 0))}, r"^means: the state dimension d is 0"),
    ],
)
def test_mixture_create_names_the_bad_field(kwargs, message):
    args = {"weights": np.array([0.5, 0.5]), "means": np.zeros((2, 1)), "covs": np.ones((2, 1, 1))}
    capacity = kwargs.pop("capacity", None)
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        GaussianMixture.create(**args, capacity=capacity)


def test_mixture_create_accepts_integer_input_and_numpy_int_capacity():
    gm = GaussianMixture.create([1, 3], [[0], [2]], [1, 2], capacity=np.int64(4))
    assert gm.capacity == 4 and jnp.issubdtype(gm.means.dtype, jnp.floating)
    np.testing.assert_allclose(np.asarray(gm.weights[:2]), [0.25, 0.75])


def test_pad_scans_pads_keeps_the_order_and_flags_cut_scans():
    rng = np.random.default_rng(0)
    scans = [rng.normal(size=(3, 2)), np.zeros((0, 2)), [], rng.normal(size=(6, 2))]
    padded = mt.pad_scans(scans, 4)
    assert padded.zs.shape == (4, 4, 2)
    np.testing.assert_array_equal(np.asarray(padded.n_measurements), [3, 0, 0, 6])
    np.testing.assert_array_equal(np.asarray(padded.overflow), [False, False, False, True])
    zs = np.asarray(padded.zs)
    np.testing.assert_array_equal(zs[0, :3], scans[0])
    np.testing.assert_array_equal(zs[3], scans[3][:4])
    assert np.isnan(zs[0, 3]).all() and np.isnan(zs[1]).all() and np.isnan(zs[2]).all()
    np.testing.assert_array_equal(np.asarray(mt.phd.measurement_mask(padded.zs)).sum(-1), [3, 0, 0, 4])


def test_pad_scans_feeds_the_phd_like_simulate():
    """A simulated run's scans, unpadded and padded again, run through the GM-PHD to the same result."""
    scenario = mt.vo_ma_linear(n_steps=5, max_measurements=24)
    sample = mt.simulate(scenario, jax.random.key(0))
    zs = np.asarray(sample.zs)
    scans = [z[np.isfinite(z).all(-1)] for z in zs]
    padded = mt.pad_scans(scans, scenario.max_measurements)
    np.testing.assert_array_equal(np.asarray(padded.zs), zs)
    filt = mt.gm_phd(scenario.model, **scenario.filter_kwargs(), capacity=12, merge_capacity=48)
    _, a = mt.run(filt, padded.zs)
    _, b = mt.run(filt, jnp.asarray(zs))
    np.testing.assert_array_equal(np.asarray(a.loglik), np.asarray(b.loglik))


@pytest.mark.parametrize(
    "scans, M, message",
    [
        ([np.ones((2, 2))], 0, r"^max_measurements: "),
        ([np.ones((2, 2))], 2.0, r"^max_measurements: "),
        ([], 4, r"^scans: expected at least one scan"),
        ([np.ones((2, 2)), np.ones((1, 3))], 4, r"^scans: .*differ in dimension m: \[2, 3\]"),
        ([np.ones((2, 2)), np.ones(2)], 4, r"^scans\[1\]: expected shape \(n, 2\)"),
        ([np.array([[1.0, np.nan]])], 4, r"^scans\[0\]: holds a NaN or infinite entry \(row 0\)"),
        ([[], np.zeros((0, 2))], 4, r"^scans: every scan is empty"),
    ],
)
def test_pad_scans_refuses_bad_input_by_name(scans, M, message):
    with pytest.raises(ValueError, match=message):
        mt.pad_scans(scans, M)
