"""gmjax.reduction.brute_force: the ISE-optimal partition, against the NumPy enumeration, every greedy
reducer (never better) and tiny weights."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_reduction import CAP, NUM_OUT, REDUCERS, ise
from test_reduction_utils import batch, index, random_components

from gmjax import GaussianMixture
from gmjax import reduction as R
from references import reduction_np as ref


def test_brute_force_matches_numpy():
    rng = np.random.default_rng(12)
    for _trial in range(3):
        w, m, P = random_components(rng, 6, 2)
        gm = index(batch([(w, m, P)], 9), 0)
        out, info = R.brute_force(gm, 3)
        val, _ = ref.brute_force(w, m, P, 3)
        np.testing.assert_allclose(float(info.cost), val, rtol=1e-9, atol=1e-14)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(4, CAP))
def test_brute_force_is_ise_optimal(seed, n):
    """No reducer that outputs a moment-preserving merge of a partition beats the exhaustive
    search; the oracle also matches the best of every other reducer's ISE."""
    rng = np.random.default_rng(seed)
    w, m, P = random_components(rng, n, 2)
    gm = GaussianMixture.create(w, m, P, capacity=CAP)
    _, info_bf = R.brute_force(gm, NUM_OUT)
    best = float(info_bf.cost)
    np.testing.assert_allclose(best, float(ise(gm, R.brute_force(gm, NUM_OUT)[0])), atol=1e-14)
    for name in ["runnalls", "west", "salmond", "kmeans", "gmrc"]:
        out, _ = REDUCERS[name](gm)
        assert best <= float(ise(gm, out)) + 1e-14, name


def test_brute_force_with_tiny_weights_picks_the_same_partition():
    """Weights ~1e-300 made every ISE underflow to 0, so the first partition (merge all) won."""
    gm = GaussianMixture.create([0.3, 0.2, 0.3, 0.2], [-1.0, 0.5, 3.0, 3.2], [1.0, 0.5, 2.0, 1.0], capacity=6)
    tiny = gm._replace(weights=gm.weights * 1e-300)
    ref, ref_info = R.brute_force(gm, 2)
    out, info = R.brute_force(tiny, 2)
    np.testing.assert_array_equal(np.asarray(info.labels), np.asarray(ref_info.labels))
    np.testing.assert_allclose(np.asarray(out.means), np.asarray(ref.means), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(out.weights) / 1e-300, np.asarray(ref.weights), rtol=1e-10)
    assert int(info.n_out) == 2
