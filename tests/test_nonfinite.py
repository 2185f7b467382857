"""Non-finite data never poisons a run silently (issue 15, item 2).

A measurement with any NaN or ``±inf`` entry is a predict-only step for every filter, raises
``StepFlags.nonfinite_measurement`` at that step only, and the filter recovers: every later estimate is
finite and equals the run in which the same rows are marked missing with NaN. A collapsed particle cloud
raises ``StepFlags.degenerate``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_contract import FILTERS  # the one table of every filter family (tests/ is on sys.path)

from gmjax import filters as F
from gmjax.filters.base import StepInputs
from gmjax.mixture import GaussianMixture as GM
from gmjax.models import StateSpaceModel, simulate

# each family in the default run; the remaining builders of a family run with -m slow
_FAST = {"kalman_filter", "ekf", "gsf_runnalls", "imm", "bank", "pf"}
BAD_ROWS = (2, 5)


@pytest.mark.parametrize(
    "name", [n if n in _FAST else pytest.param(n, marks=pytest.mark.slow) for n in sorted(FILTERS)]
)
def test_infinite_measurement_is_a_flagged_predict_only_step_and_the_filter_recovers(name):
    make_scenario, build, _ = FILTERS[name]
    sc = make_scenario()
    filt = build(sc)
    zs = simulate(sc, jax.random.key(3))[1]
    if name == "kalman_filter":
        zs = zs[..., :1]
    bad = zs.at[BAD_ROWS[0], 0].set(jnp.inf).at[BAD_ROWS[1], -1].set(-jnp.inf)
    missing = zs.at[BAD_ROWS[0]].set(jnp.nan).at[BAD_ROWS[1]].set(jnp.nan)
    run = jax.jit(jax.vmap(lambda z: F.run(filt, z, key=jax.random.key(1))[1]))
    infos = run(jnp.stack([zs, bad, missing]))
    clean, inf_run, nan_run = (jax.tree_util.tree_map(lambda a, i=i: a[i], infos) for i in range(3))
    # every estimate finite, before and after the bad steps
    for i in (inf_run, nan_run):
        assert np.all(np.isfinite(np.asarray(i.mean))) and np.all(np.isfinite(np.asarray(i.cov)))
        assert np.all(np.isfinite(np.asarray(i.loglik)))
    # the flag sits exactly on the bad steps; an inf is treated as the missing-measurement NaN
    expected = np.isin(np.arange(zs.shape[0]), BAD_ROWS)
    np.testing.assert_array_equal(np.asarray(inf_run.flags.nonfinite_measurement), expected)
    np.testing.assert_array_equal(np.asarray(nan_run.flags.nonfinite_measurement), expected)
    assert not np.any(np.asarray(clean.flags.nonfinite_measurement))
    assert np.all(np.asarray(inf_run.flags.any())[expected])
    # (to rounding: the three runs are batched lanes of one vmap)
    np.testing.assert_allclose(np.asarray(inf_run.mean), np.asarray(nan_run.mean), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(inf_run.loglik), np.asarray(nan_run.loglik), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(inf_run.loglik)[expected], 0.0)
    # before the first bad step nothing changes
    k = BAD_ROWS[0]
    np.testing.assert_allclose(
        np.asarray(inf_run.mean[:k]), np.asarray(clean.mean[:k]), rtol=1e-12, atol=1e-12
    )


def test_is_missing_decides_on_every_non_finite_entry():
    from gmjax.filters._core import is_missing

    for z, want in (
        ([0.0, 1.0], False),
        ([np.inf, 1.0], True),
        ([0.0, -np.inf], True),
        ([np.nan, 0.0], True),
    ):
        assert bool(is_missing(jnp.asarray(z))) is want


def _linear_model(r: float) -> StateSpaceModel:
    A = jnp.asarray([[1.0, 1.0], [0.0, 1.0]])
    H = jnp.asarray([[1.0, 0.0]])
    return StateSpaceModel(
        lambda x, t: A @ x,
        lambda x, t: H @ x,
        GM.create([1.0], [np.zeros(2)], [0.1 * np.eye(2)]),
        GM.create([1.0], [[0.0]], [[[r]]]),
        GM.create([1.0], [np.zeros(2)], [np.eye(2)]),
    )


def test_collapsed_particle_cloud_is_flagged_degenerate():
    """A measurement far sharper than the particle spacing leaves one particle with all the weight:
    ESS ~ 1, flagged; an ordinary measurement noise on the same particles is not flagged."""
    k_init, k_pred, k_upd = jax.random.split(jax.random.key(0), 3)
    one = StepInputs(t=1)
    z = jnp.asarray([0.3])
    results = {}
    for r in (0.5, 1e-8):
        flt = F.build_pf(_linear_model(r), 200)
        st = flt.predict(flt.params, flt.init(flt.params, key=k_init), one, key=k_pred)
        _, info = jax.jit(flt.update)(flt.params, st, z, one, key=k_upd)
        results[r] = info
    sharp, ordinary = results[1e-8], results[0.5]
    assert float(sharp.extra["ess"]) < 1.5 and bool(sharp.flags.degenerate)
    assert float(ordinary.extra["ess"]) > 10 and not bool(ordinary.flags.any())
    assert np.all(np.isfinite(np.asarray(sharp.mean)))
