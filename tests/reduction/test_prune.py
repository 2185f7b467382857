"""gmjax.reduction.prune: censored pruning by the order statistic (seed 000 eqs 19-22), threshold and
top-N pruning."""

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


def test_prune_censored_order_statistic():
    """Seed 000 eqs 19–22 on a hand example: sorted weights .05 .1 .15 .3 .4; gamma_n =
    1, .95, .85, .7, .4; rho = .9 -> n_max = 2, N = 5 - 2 + 1 = 4; eq 41 rescales by 1/.95."""
    w = np.array([0.3, 0.05, 0.4, 0.15, 0.1])
    gm = GaussianMixture.create(w, np.arange(5.0), np.ones(5), capacity=7)
    out, info = R.prune_censored(gm, 0.9)
    np.testing.assert_allclose(np.asarray(out.weights[:4]), np.array([0.4, 0.3, 0.15, 0.1]) / 0.95)
    assert int(info.n_out) == 4 and abs(float(info.pruned_mass) - 0.05) < 1e-15
    np.testing.assert_array_equal(np.asarray(info.labels), [1, -1, 0, 2, 3, -1, -1])
    out, info = R.prune_censored(gm, 0.9, 2)  # N_u = 2
    np.testing.assert_allclose(np.asarray(out.weights[:2]), np.array([0.4, 0.3]) / 0.7)
    out, _ = R.prune_threshold(gm, 0.12)
    np.testing.assert_allclose(np.asarray(out.weights[:3]), np.array([0.4, 0.3, 0.15]) / 0.85)
    out, info = R.prune_top(gm, 2, capacity=2)
    assert out.capacity == 2 and abs(float(info.pruned_mass) - 0.3) < 1e-15


def test_pruning_matches_numpy():
    rng = np.random.default_rng(3)
    for _trial in range(30):
        w, m, P = random_components(rng, int(rng.integers(3, 10)), 2, wr=(1e-3, 0.3))
        gm = index(batch([(w, m, P)], 9), 0)
        for out, (keep, wk) in (
            (R.prune_threshold(gm, 0.05)[0], ref.prune_threshold(w, 0.05)),
            (R.prune_top(gm, 3)[0], ref.prune_top(w, 3)),
            (R.prune_censored(gm, 0.9)[0], ref.prune_censored(w, 0.9)),
            (R.prune_censored(gm, 0.9544, 4)[0], ref.prune_censored(w, 0.9544, 4)),
        ):
            n = len(keep)
            assert int(np.sum(np.asarray(out.mask))) == n
            np.testing.assert_allclose(np.asarray(out.weights[:n]), wk, atol=1e-14)
            np.testing.assert_allclose(np.asarray(out.means[:n]), m[keep], atol=0)
