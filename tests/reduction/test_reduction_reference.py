"""gmjax.reduction against the plain NumPy implementations in references/reduction_np.py.

Runnalls, West, Salmond and k-means: 200 random mixtures (seed 000 ranges, 6-12 live components in
a capacity-12 batch, d = 1 and 2), all reduced in one vmapped call; the merge sequence and labels
must be identical and every output equal to 1e-10.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from test_reduction_utils import batch, index, random_components  # noqa: E402

from gmjax import reduction as R  # noqa: E402
from references import reduction_np as ref  # noqa: E402

N_MIX = 200
CAP = 12
NUM_OUT = 4


def _mixtures(d, seed, n=N_MIX):
    rng = np.random.default_rng(seed)
    comps = [random_components(rng, int(rng.integers(6, CAP + 1)), d) for _ in range(n)]
    return comps, batch(comps, CAP)


def _compare_outputs(out, info, r, b, n):
    n_out = int(info.n_out[b])
    assert n_out == len(r["w"])
    np.testing.assert_allclose(np.asarray(out.weights[b, :n_out]), r["w"], rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.means[b, :n_out]), r["m"], rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.covs[b, :n_out]), r["P"], rtol=0, atol=1e-10)
    assert not np.asarray(out.mask[b, n_out:]).any()
    np.testing.assert_array_equal(np.asarray(info.labels[b, :n]), r["labels"])
    assert (np.asarray(info.labels[b, n:]) == -1).all()


@pytest.mark.parametrize("d", [1, 2])
@pytest.mark.parametrize("name", ["runnalls", "salmond", "west", "west_ise"])
def test_greedy_matches_numpy(name, d):
    comps, gm = _mixtures(d, seed=10 * d + len(name))
    if name == "west_ise":
        fn = jax.jit(jax.vmap(lambda g: R.west(g, NUM_OUT, metric="ise")))
        reff = lambda w, m, P: ref.west(w, m, P, NUM_OUT, metric="ise")  # noqa: E731
    else:
        fn = jax.jit(jax.vmap(lambda g: getattr(R, name)(g, NUM_OUT)))
        reff = lambda w, m, P: getattr(ref, name)(w, m, P, NUM_OUT)  # noqa: E731
    out, info = fn(gm)
    for b, (w, m, P) in enumerate(comps):
        r = reff(w, m, P)
        merges = [tuple(int(v) for v in row) for row in np.asarray(info.aux["merges"][b]) if row[0] >= 0]
        assert merges == r["merges"], f"mixture {b}: merge sequence differs"
        _compare_outputs(out, info, r, b, len(w))
        np.testing.assert_allclose(float(info.cost[b]), r["cost"], rtol=1e-9, atol=1e-12)


def test_greedy_threshold_matches_numpy():
    """A finite cost threshold stops Runnalls/Salmond at the same step as the reference."""
    comps, gm = _mixtures(2, seed=77, n=20)
    for name, thr in (("runnalls", 0.02), ("salmond", 0.05)):
        out, info = jax.vmap(lambda g: getattr(R, name)(g, 1, thr))(gm)
        for b, (w, m, P) in enumerate(comps):
            r = getattr(ref, name)(w, m, P, 1, thr)
            _compare_outputs(out, info, r, b, len(w))


@pytest.mark.parametrize("name", ["runnalls", "salmond"])
def test_greedy_ties_match_numpy(name):
    """Many exactly equal pair costs (equal weights and covariances, means on an integer lattice,
    repeated components): the selection takes the first minimiser in row-major order, as the
    reference's ``argmin`` over the upper triangle does. (In 1-D: a 2-D lattice also
    has pairs equal only mathematically, e.g. offsets (1.5, 0.5) and (0.5, 1.5), whose costs round
    differently here and in NumPy.)"""
    d = 1
    rng = np.random.default_rng(3 + d)
    comps = []
    for _ in range(40):
        n = int(rng.integers(6, CAP + 1))
        m = rng.integers(0, 3, (n, d)).astype(float)
        comps.append((np.full(n, 1.0 / n), m, np.tile(np.eye(d), (n, 1, 1))))
    gm = batch(comps, CAP)
    out, info = jax.jit(jax.vmap(lambda g: getattr(R, name)(g, 2)))(gm)
    for b, (w, m, P) in enumerate(comps):
        r = getattr(ref, name)(w, m, P, 2)
        merges = [tuple(int(v) for v in row) for row in np.asarray(info.aux["merges"][b]) if row[0] >= 0]
        assert merges == r["merges"], f"mixture {b}: merge sequence differs"
        _compare_outputs(out, info, r, b, len(w))


@pytest.mark.parametrize("d", [1, 2])
def test_kmeans_matches_numpy(d):
    comps, gm = _mixtures(d, seed=5 + d)
    out, info = jax.jit(jax.vmap(lambda g: R.kmeans(g, NUM_OUT)))(gm)
    for b, (w, m, P) in enumerate(comps):
        r = ref.kmeans(w, m, P, NUM_OUT)
        _compare_outputs(out, info, r, b, len(w))
        assert int(info.aux["iterations"][b]) == r["iterations"]


def test_gmrc_matches_numpy():
    comps, gm = _mixtures(2, seed=31, n=40)
    out, info = jax.jit(jax.vmap(lambda g: R.gmrc(g, NUM_OUT)))(gm)
    for b, (w, m, P) in enumerate(comps):
        r = ref.gmrc(w, m, P, NUM_OUT)
        _compare_outputs(out, info, r, b, len(w))


def test_williams_matches_numpy():
    """Same actions (merges and deletions) and outputs as a reference that scores every
    candidate with a direct ISE evaluation."""
    rng = np.random.default_rng(41)
    comps = [random_components(rng, int(rng.integers(5, 8)), 2) for _ in range(12)]
    for w, m, P in comps:
        gm = batch([(w, m, P)], 9)
        out, info = R.williams(index(gm, 0), 3)
        r = ref.williams(w, m, P, 3)
        acts = [tuple(int(v) for v in row) for row in np.asarray(info.aux["actions"]) if row[0] >= 0]
        assert acts == r["actions"]
        n_out = int(info.n_out)
        np.testing.assert_allclose(np.asarray(out.weights[:n_out]), r["w"], atol=1e-10)
        np.testing.assert_allclose(np.asarray(out.means[:n_out]), r["m"], atol=1e-10)
        np.testing.assert_allclose(np.asarray(out.covs[:n_out]), r["P"], atol=1e-10)
        np.testing.assert_allclose(float(info.cost), r["cost"], rtol=1e-8, atol=1e-13)


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


def test_brute_force_matches_numpy():
    rng = np.random.default_rng(12)
    for _trial in range(3):
        w, m, P = random_components(rng, 6, 2)
        gm = index(batch([(w, m, P)], 9), 0)
        out, info = R.brute_force(gm, 3)
        val, _ = ref.brute_force(w, m, P, 3)
        np.testing.assert_allclose(float(info.cost), val, rtol=1e-9, atol=1e-14)


def test_cowa_weights_match_numpy():
    """COWA's constrained QP (jitted active set) equals the NumPy active set and SciPy SLSQP."""
    from scipy.optimize import minimize

    from gmjax.reduction.cowa import optimal_weights

    rng = np.random.default_rng(4)
    for _trial in range(10):
        n = 6
        X = rng.normal(size=(n, n + 2))
        S = X @ X.T + 0.1 * np.eye(n)
        b = rng.normal(size=n)
        w_ref, act_ref = ref.cowa_weights(S, b, 1.0)
        w, act = optimal_weights(S, b, np.ones(n, bool), 1.0, n)
        np.testing.assert_allclose(np.asarray(w), w_ref, atol=1e-10)
        res = minimize(
            lambda x: x @ S @ x - 2 * b @ x,
            np.full(n, 1 / n),
            method="SLSQP",
            bounds=[(0, None)] * n,
            constraints=[{"type": "eq", "fun": lambda x: x.sum() - 1}],
            options={"ftol": 1e-14, "maxiter": 500},
        )
        # the active-set answer is feasible and at least as good as SLSQP's when no weight is cut
        f = lambda x: x @ S @ x - 2 * b @ x  # noqa: E731
        if act_ref.all():
            assert f(np.asarray(w)) <= res.fun + 1e-9
