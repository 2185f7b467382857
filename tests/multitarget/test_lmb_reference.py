"""The NumPy GM-LMB reference (references/lmb_np.py) by itself: the Gibbs truncation against the exact
enumeration, closed forms, the sampler's invariants, the prediction, the cardinality pmf and the pruning."""

import itertools

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from references import lmb_np as lmb

H2 = np.eye(2)
R2 = 0.5 * np.eye(2)


def _tracks(r, means, covs=None, J=2, mask=None):
    """Single-component tracks (slot 0) labelled ``(0, i)``; ``mask`` False leaves a slot empty."""
    r = np.asarray(r, float)
    N = len(r)
    means = np.asarray(means, float).reshape(N, -1)
    d = means.shape[1]
    mask = np.ones(N, bool) if mask is None else np.asarray(mask, bool)
    t = lmb.empty_tracks(N, J, d)
    for i in range(N):
        if mask[i]:
            t.r[i] = r[i]
            t.labels[i] = (0, i)
            t.mask[i] = True
            t.w[i, 0] = 1.0
            t.m[i, 0] = means[i]
            t.P[i, 0] = np.eye(d) if covs is None else covs[i]
            t.cmask[i, 0] = True
    return t


def _update(tracks, Z, G, seed, **kw):
    u = np.random.default_rng(seed).random((G - 1, len(tracks.r)))
    args = dict(n_tracks=len(tracks.r), n_components=tracks.w.shape[1], existence_threshold=1e-3)
    args.update(component_threshold=1e-5)
    args.update(kw)
    p_d, lam, c = args.pop("p_d", 0.8), args.pop("clutter_rate", 2.0), args.pop("clutter_density", 0.01)
    return lmb.update(tracks, Z, H2, R2, p_d, lam, c, u, **args)


# --------------------------------------------------------------------------------- 1. Gibbs == exact
@pytest.mark.parametrize("seed,N,M", [(0, 2, 2), (1, 3, 2), (2, 2, 3), (3, 3, 3), (4, 3, 3)])
def test_gibbs_visits_every_hypothesis_on_random_costs(seed, N, M):
    rng = np.random.default_rng(seed)
    r = rng.uniform(0.4, 0.6, N)
    p_d = 0.5
    L = np.empty((N, M + 2))
    L[:, 0] = np.log(1 - r)
    L[:, 1] = np.log(r * (1 - p_d))
    L[:, 2:] = np.log(r * p_d)[:, None] + rng.uniform(-0.5, 0.5, (N, M))
    if seed == 4:
        L[1, 2] = -np.inf  # an impossible association
    u = rng.random((1999, N))
    samples = lmb.gibbs(L, np.ones(N, bool), u)
    kept = lmb.unique_rows(samples)
    weights, r_post, beta, log_norm = lmb.hypothesis_weights(L, samples, kept)
    exact = lmb.exact_marginals(L)
    assert kept.sum() == exact.n_hypotheses
    assert np.all(weights[kept] > 0) and np.all(weights[~kept] == 0)
    np.testing.assert_allclose(weights.sum(), 1.0, atol=1e-12)
    np.testing.assert_allclose(r_post, exact.r, atol=1e-12, rtol=0)
    np.testing.assert_allclose(beta, exact.beta, atol=1e-12, rtol=0)
    np.testing.assert_allclose(log_norm, exact.log_norm, atol=1e-12, rtol=0)
    # a short chain misses hypotheses: its normaliser is a lower bound
    short = lmb.gibbs(L, np.ones(N, bool), u[:10])
    k_short = lmb.unique_rows(short)
    assert k_short.sum() < exact.n_hypotheses
    assert lmb.hypothesis_weights(L, short, k_short)[3] < exact.log_norm


@pytest.mark.parametrize("seed", range(3))
def test_update_marginals_equal_enumeration(seed):
    rng = np.random.default_rng(10 + seed)
    means = 0.5 * np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    tr = _tracks(rng.uniform(0.4, 0.7, 3), means)
    # a second component on track 0: the detection cost sums over components
    tr.w[0, :] = (0.6, 0.4)
    tr.m[0, 1] = (0.2, -0.2)
    tr.P[0, 1] = 2.0 * np.eye(2)
    tr.cmask[0, 1] = True
    Z = 0.5 * np.array([[0.3, 0.1], [1.0, 0.2], [np.nan, np.nan], [0.2, 1.0]]) + rng.normal(0, 0.1, (4, 2))
    res = _update(tr, Z, 2000, seed, n_components=8, p_d=0.5, clutter_rate=1.0, clutter_density=0.1)
    exact = lmb.exact_marginals(res.log_eta)
    assert np.all(np.isneginf(res.log_eta[:, 4]))  # the absent z_3
    assert res.kept.sum() == exact.n_hypotheses == 86
    np.testing.assert_allclose(res.r, exact.r, atol=1e-12, rtol=0)
    np.testing.assert_allclose(res.beta, exact.beta, atol=1e-12, rtol=0)
    np.testing.assert_allclose(res.loglik, exact.log_norm - 1.0 + 3 * np.log(0.1), atol=1e-12, rtol=0)
    # the posterior (every r' here is above the threshold, capacity 3): r and labels in order
    np.testing.assert_allclose(res.tracks.r, res.r)
    np.testing.assert_array_equal(res.tracks.labels, tr.labels)
    for i in range(3):
        w = res.tracks.w[i][res.tracks.cmask[i]]
        assert len(w) == (8 if i == 0 else 4)  # (1 + 3 present) x (2 or 1) components
        assert np.all(np.diff(w) <= 0)
        np.testing.assert_allclose(w.sum(), 1.0, atol=1e-12)


# ------------------------------------------------------------------------------- 2. closed form
@pytest.mark.parametrize("r,p_d", [(0.6, 0.9), (0.25, 0.5), (1.0, 0.7)])
def test_single_track_closed_form(r, p_d):
    m0, P0 = np.array([1.0, -1.0]), np.array([[2.0, 0.3], [0.3, 1.0]])
    tr = _tracks([r], [m0], [P0], J=2)
    z = np.array([1.4, -0.2])
    res = _update(tr, z[None], 50, 0, p_d=p_d)
    kappa = 2.0 * 0.01
    S = H2 @ P0 @ H2.T + R2
    q = multivariate_normal(H2 @ m0, S).pdf(z)
    miss, det = r * (1 - p_d), r * p_d * q / kappa
    r_post = (miss + det) / (1 - r + miss + det)
    np.testing.assert_allclose(res.r[0], r_post, rtol=1e-12)
    np.testing.assert_allclose(res.beta[0], [miss, det] / (1 - r + miss + det), rtol=1e-12)
    np.testing.assert_allclose(res.loglik, np.log(1 - r + miss + det) - 2.0 + np.log(kappa), rtol=1e-12)
    assert res.kept.sum() == (2 if r == 1.0 else 3)
    K = P0 @ H2.T @ np.linalg.inv(S)
    m_kf, P_kf = m0 + K @ (z - H2 @ m0), (np.eye(2) - K @ H2) @ P0
    post = res.tracks
    np.testing.assert_allclose(post.r[0], r_post, rtol=1e-12)
    blocks = {"missed": (miss / (miss + det), m0, P0), "detected": (det / (miss + det), m_kf, P_kf)}
    order = sorted(blocks.values(), key=lambda b: -b[0])
    for k, (wk, mk, Pk) in enumerate(order):
        np.testing.assert_allclose(post.w[0, k], wk, rtol=1e-12)
        np.testing.assert_allclose(post.m[0, k], mk, rtol=1e-12)
        np.testing.assert_allclose(post.P[0, k], Pk, rtol=1e-12)


def test_far_measurement_is_clutter():
    """A measurement far from the track: q underflows to 0, the track is only missed or absent."""
    r, p_d = 0.7, 0.9
    tr = _tracks([r], [[0.0, 0.0]], J=1)
    res = _update(tr, np.array([[1e3, 1e3]]), 20, 1, p_d=p_d)
    assert np.isneginf(res.log_eta[0, 2])
    np.testing.assert_allclose(res.r[0], r * (1 - p_d) / (1 - r * p_d), rtol=1e-12)
    np.testing.assert_allclose(res.tracks.m[0, 0], [0.0, 0.0])
    assert res.tracks.w[0, 0] == 1.0 and res.tracks.cmask[0].tolist() == [True]


# ----------------------------------------------------------------------------- 3. sampler invariants
def test_samples_use_each_measurement_once_and_empty_tracks_stay_absent():
    rng = np.random.default_rng(3)
    N, M = 7, 4
    mask = np.array([1, 0, 1, 1, 0, 1, 1], bool)
    means = rng.uniform(0, 3, (N, 2))
    tr = _tracks(rng.uniform(0.5, 0.99, N), means, mask=mask)
    Z = means[[0, 2, 3, 5]] + rng.normal(0, 0.3, (M, 2))
    res = _update(tr, Z, 300, 7, p_d=0.95)
    s = res.samples
    assert s.shape == (300, N)
    np.testing.assert_array_equal(s[0], mask.astype(int))
    assert np.all(s[:, ~mask] == 0)
    assert np.all((s >= 0) & (s <= M + 1))
    for row in s:
        det = row[row >= 2]
        assert len(det) == len(set(det.tolist()))
    assert res.kept[0] and res.kept.sum() == len({tuple(row) for row in s})
    assert np.all(res.r[~mask] == 0) and np.all(res.beta[~mask] == 0)
    # a row's weight is the product of its costs, normalised over the kept rows
    logw = np.array([sum(res.log_eta[i, row[i]] for i in range(N)) for row in s[res.kept]])
    np.testing.assert_allclose(res.weights[res.kept], np.exp(logw - np.logaddexp.reduce(logw)), rtol=1e-12)


# ------------------------------------------------------------------------------ 4. predict, pmf
def test_predict_survivors_and_births():
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = 0.1 * np.eye(2)
    tr = _tracks([0.9, 0.0, 0.4], [[1.0, 2.0], [0, 0], [3.0, -1.0]], mask=[1, 0, 1], J=2)
    tr.labels[2] = (3, 1)
    tr.w[2] = (0.7, 0.3)
    tr.m[2, 1] = (0.5, 0.5)
    tr.P[2, 1] = 2 * np.eye(2)
    tr.cmask[2, 1] = True
    bw = np.array([0.05, 0.2, 0.5])
    bm = np.array([[0.0, 1.0], [9.0, 9.0], [5.0, 0.0]])
    bP = np.stack([np.eye(2), 3 * np.eye(2), 4 * np.eye(2)])
    pred = lmb.predict(tr, F, Q, 0.95, bw, bm, bP, [True, False, True], step=4)
    assert pred.r.shape == (6,) and pred.w.shape == (6, 2)
    np.testing.assert_allclose(pred.r, [0.95 * 0.9, 0, 0.95 * 0.4, 0.05, 0, 0.5])
    np.testing.assert_array_equal(pred.mask, [1, 0, 1, 1, 0, 1])
    np.testing.assert_array_equal(pred.labels, [[0, 0], [-1, -1], [3, 1], [4, 0], [-1, -1], [4, 2]])
    for i, c in [(0, 0), (2, 0), (2, 1)]:
        np.testing.assert_allclose(pred.m[i, c], F @ tr.m[i, c])
        np.testing.assert_allclose(pred.P[i, c], F @ tr.P[i, c] @ F.T + Q)
    np.testing.assert_array_equal(pred.w[2], tr.w[2])
    np.testing.assert_array_equal(pred.cmask, [[1, 0], [0, 0], [1, 1], [1, 0], [0, 0], [1, 0]])
    for b, i in [(0, 3), (2, 5)]:
        np.testing.assert_array_equal(pred.m[i, 0], bm[b])
        np.testing.assert_array_equal(pred.P[i, 0], bP[b])
        assert pred.w[i].tolist() == [1.0, 0.0]
    # empty slots: weight 0, mean 0, identity covariance
    np.testing.assert_array_equal(pred.m[4], 0)
    np.testing.assert_array_equal(pred.P[4], np.tile(np.eye(2), (2, 1, 1)))
    with pytest.raises(ValueError):
        lmb.predict(tr, F, Q, 0.95, [1.5], bm[:1], bP[:1], [True], step=1)


def test_cardinality_pmf_against_enumeration():
    r = np.array([0.9, 0.3, 0.0, 0.55, 0.7])
    mask = np.array([1, 1, 0, 1, 1], bool)
    rho = lmb.cardinality_pmf(r, mask)
    brute = np.zeros(6)
    live = r[mask]
    for e in itertools.product([0, 1], repeat=4):
        brute[sum(e)] += np.prod([x if ei else 1 - x for x, ei in zip(live, e)])
    assert rho.shape == (6,)
    np.testing.assert_allclose(rho.sum(), 1.0, atol=1e-15)
    np.testing.assert_allclose(rho, brute, atol=1e-15)


def test_extract():
    tr = _tracks([0.9, 0.2, 0.85, 0.6, 0.0], np.arange(10.0).reshape(5, 2), mask=[1, 1, 1, 1, 0])
    est = lmb.extract(tr, 4)
    rho = lmb.cardinality_pmf(tr.r, tr.mask)
    assert est.n_hat == int(np.argmax(rho)) == 3
    np.testing.assert_array_equal(est.states[:3], tr.m[[0, 2, 3], 0])
    np.testing.assert_array_equal(est.labels, [[0, 0], [0, 2], [0, 3], [-1, -1]])
    np.testing.assert_array_equal(est.mask, [1, 1, 1, 0])
    # ties: n_hat = 0 for one track at r = 0.5; equal r's in slot order; capacity E below n_hat
    assert lmb.extract(_tracks([0.5], [[1.0, 1.0]]), 2).n_hat == 0
    est = lmb.extract(_tracks([0.8, 0.9, 0.8], np.arange(6.0).reshape(3, 2)), 2)
    assert est.n_hat == 3 and est.labels.tolist() == [[0, 1], [0, 0]]


# ------------------------------------------------------------------------ 5. pruning and capacity
def test_capacity_keeps_the_largest_in_original_order():
    r = np.array([0.5, 0.9, 0.0005, 0.7, 0.3, 0.95, 0.8])
    tr = _tracks(r, np.zeros((7, 2)), mask=[1, 1, 1, 1, 1, 1, 0])
    # no measurement: every track is missed or absent independently, r' near r (1 - P_D) / (1 - r P_D)
    Z = np.full((2, 2), np.nan)
    res = _update(tr, Z, 400, 2, n_tracks=3, p_d=0.5)
    np.testing.assert_allclose(res.r[:6], r[:6] * 0.5 / (1 - r[:6] * 0.5), atol=0.02)
    assert res.r[2] < 1e-3 and res.r[6] == 0 and res.overflow
    # the 3 largest r' (slots 1, 5, 3) in slot order
    assert sorted(np.argsort(-res.r, kind="stable")[:3].tolist()) == [1, 3, 5]
    np.testing.assert_array_equal(res.tracks.labels, [[0, 1], [0, 3], [0, 5]])
    np.testing.assert_allclose(res.tracks.r, res.r[[1, 3, 5]])
    np.testing.assert_array_equal(res.tracks.m, np.zeros((3, 2, 2)))
    # capacity 5: slot 2 falls under the existence threshold, no overflow, empty slot padded
    res = _update(tr, Z, 400, 2, n_tracks=5, p_d=0.5)
    assert not res.overflow
    np.testing.assert_array_equal(res.tracks.labels, [[0, 0], [0, 1], [0, 3], [0, 4], [0, 5]])
    res = _update(tr, Z, 400, 2, n_tracks=6, p_d=0.5)
    assert not res.overflow and not res.tracks.mask[5] and res.tracks.r[5] == 0
    np.testing.assert_array_equal(res.tracks.P[5], np.tile(np.eye(2), (2, 1, 1)))
    # ties in r' (a single Gibbs row, all missed: r' = 1 each): the lower slots win
    res = _update(_tracks([0.6, 0.3, 0.6], np.zeros((3, 2))), Z, 1, 0, n_tracks=2)
    np.testing.assert_array_equal(res.r, 1.0)
    assert res.overflow and res.tracks.labels.tolist() == [[0, 0], [0, 1]]


def test_component_reduction():
    """Step 7: strict threshold, J heaviest in decreasing weight, renormalised."""
    tr = _tracks([0.9], [[0.0, 0.0]], J=3)
    Z = np.array([[0.2, 0.0], [40.0, 0.0], [-0.3, 0.2]])
    full = _update(tr, Z, 100, 0, n_components=4, component_threshold=0.0)
    w_all = full.tracks.w[0]
    res = _update(tr, Z, 100, 0, n_components=2, component_threshold=1e-5)
    # the far z_2 gives a weight-0 block: live (mask True) without threshold, dropped with one
    assert full.tracks.cmask[0].sum() == 4 and w_all[3] == 0
    np.testing.assert_allclose(res.tracks.w[0, :2], w_all[:2] / w_all[:2].sum(), rtol=1e-12)
    np.testing.assert_array_equal(res.tracks.m[0, :2], full.tracks.m[0, :2])
    assert res.tracks.cmask[0].tolist() == [True, True]
    assert np.all(np.diff(w_all) <= 0) and w_all[0] > w_all[1]
    # nothing reaches the threshold: the heaviest is kept alone
    res = _update(tr, Z, 100, 0, n_components=2, component_threshold=2.0)
    assert res.tracks.cmask[0].tolist() == [True, False] and res.tracks.w[0].tolist() == [1.0, 0.0]
    np.testing.assert_array_equal(res.tracks.m[0, 0], full.tracks.m[0, 0])


def test_run_tracks_two_targets():
    rng = np.random.default_rng(5)
    F, Q = np.eye(2), 0.01 * np.eye(2)
    truth = np.array([[0.0, 0.0], [5.0, 5.0]])
    Zs = [np.vstack([truth + rng.normal(0, 0.3, (2, 2)), rng.uniform(-10, 10, (1, 2))]) for _ in range(4)]
    us = [rng.random((60, 4 + 2)) for _ in range(4)]
    out = lmb.run(
        lmb.empty_tracks(4, 3, 2),
        Zs,
        us,
        F,
        Q,
        H2,
        0.09 * np.eye(2),
        p_s=0.99,
        p_d=0.95,
        clutter_rate=1.0,
        clutter_density=1 / 400,
        birth_w=[0.1, 0.1],
        birth_m=truth,
        birth_P=np.stack([np.eye(2)] * 2),
        n_tracks=4,
        n_components=3,
    )
    est = out[-1]["estimates"]
    assert est.n_hat == 2
    np.testing.assert_allclose(np.sort(est.states[est.mask], axis=0), truth, atol=0.5)
    assert sorted(map(tuple, est.labels[est.mask].tolist())) == [(1, 0), (1, 1)]
    assert all(np.isfinite(o["loglik"]) for o in out)


def test_gibbs_draw_rule_and_sweep_order():
    """The smallest a with cum_a > u cum_{M+1}; later tracks see the new choice of earlier ones."""
    L = np.array([[-np.inf, -np.inf, 0.0], [np.log(0.5), np.log(0.5), 0.0]])
    # row 1: track 0 must take z_1; track 1 then sees z_1 taken: p = [1, 1, 0], threshold 2 u
    s = lmb.gibbs(L, np.ones(2, bool), np.array([[0.9, 0.4], [0.0, 0.6]]))
    np.testing.assert_array_equal(s, [[1, 1], [2, 0], [2, 1]])
    # u = 0 takes the first feasible choice (track 0: a = 1); a track with no feasible choice (track 2:
    # z_1 taken by track 1, a = 0, 1 impossible) keeps its gamma, the start's infeasible 1
    L3 = np.array([[-np.inf, np.log(0.3), np.log(0.2)], [-np.inf, -np.inf, 0.0], [-np.inf, -np.inf, 0.0]])
    s = lmb.gibbs(L3, np.ones(3, bool), np.zeros((2, 3)))
    np.testing.assert_array_equal(s, [[1, 1, 1], [1, 2, 1], [1, 2, 1]])
    # an empty slot always takes 0 whatever u
    s = lmb.gibbs(np.array([[0.0, -np.inf, -np.inf]]), np.zeros(1, bool), np.array([[0.999999]]))
    np.testing.assert_array_equal(s, [[0], [0]])


def test_degenerate_existence():
    """r = 1 with P_D = 1 forces a detection; a zero birth weight gives a track that ends empty."""
    tr = _tracks([1.0, 0.0], [[0.0, 0.0], [1.0, 1.0]])
    res = _update(tr, np.array([[0.1, 0.0]]), 5, 0, p_d=1.0)
    assert np.isneginf(res.log_eta[0, :2]).all() and np.isneginf(res.log_eta[1, 1:]).all()
    assert res.samples[1:].tolist() == [[2, 0]] * 4 and res.weights[0] == 0
    np.testing.assert_allclose(res.r, [1.0, 0.0])
    assert res.tracks.mask.tolist() == [True, False] and res.tracks.labels[1].tolist() == [-1, -1]
    # a single row (the start) of zero weight: nothing survives, loglik = -inf
    res = _update(tr, np.array([[0.1, 0.0]]), 1, 0, p_d=1.0)
    assert np.isneginf(res.loglik) and not res.tracks.mask.any() and np.all(res.r == 0)
