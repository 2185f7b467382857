"""gmjax.reduction.vo_ma: the mass an output capacity drops is reported."""

from __future__ import annotations

import jax
import numpy as np
from test_reduction_utils import (
    batch,
    index,
    random_components,
)

from gmjax import reduction as R
from gmjax.metrics import ise as _ise_eager
from gmjax.mixture import GaussianMixture
from references import reduction_np as ref

ise = jax.jit(_ise_eager)


def test_vo_ma_reports_the_mass_its_output_capacity_drops():
    """Vo & Ma keeps the J_max heaviest and restores the total weight; a smaller output ``capacity``
    then keeps the heaviest of those without renormalising. The weight that capacity drops is
    reported in ``pruned_mass`` (until the ``finalize_info`` refactor it was left out), so the
    output and the pruned mass account for every component."""
    w = np.array([0.4, 0.3, 0.2, 0.1])
    gm = GaussianMixture.create(w, np.array([0.0, 10.0, 20.0, 30.0]), np.ones(4))  # nothing merges
    out, info = R.vo_ma(gm, 1e-3, 1.0, capacity=2)
    assert bool(info.overflow) and int(info.n_out) == 2
    np.testing.assert_allclose(np.asarray(out.weights), [0.4, 0.3], rtol=1e-15)
    assert abs(float(info.pruned_mass) - 0.3) < 1e-15
    # 0.1 pruned by the threshold (the survivors renormalised to the total), then 0.2 / 0.9 by capacity
    out, info = R.vo_ma(gm, 0.15, 1.0, capacity=2)
    np.testing.assert_allclose(np.asarray(out.weights), np.array([0.4, 0.3]) / 0.9, rtol=1e-15)
    assert abs(float(info.pruned_mass) - (0.1 + 0.2 / 0.9)) < 1e-15


def test_vo_ma_matches_numpy():
    rng = np.random.default_rng(8)
    for _trial in range(30):
        w, m, P = random_components(rng, int(rng.integers(4, 10)), 2, wr=(1e-3, 0.2))
        gm = index(batch([(w, m, P)], 9), 0)
        out, info = R.vo_ma(gm, 0.02, 2.0, 5)
        wr, mr, Pr = ref.vo_ma(w, m, P, 0.02, 2.0, 5)
        n_out = int(info.n_out)
        assert n_out == len(wr)
        order = np.argsort(-wr, kind="stable")
        np.testing.assert_allclose(np.asarray(out.weights[:n_out]), wr[order], atol=1e-12)
        np.testing.assert_allclose(np.asarray(out.means[:n_out]), mr[order], atol=1e-12)
        np.testing.assert_allclose(np.asarray(out.covs[:n_out]), Pr[order], atol=1e-12)
