"""Track metrics of gmjax.multitarget.tracks: OSPA^(2) against a brute-force reference, label switches."""

import numpy as np
import pytest

from gmjax.multitarget.tracks import LabelSwitches, label_switches, ospa2
from references.ospa2_np import ospa2_ref

K = 6
POOL = np.array([[0, 0], [0, 1], [2, 0], [3, 1]])  # the labels (birth step, birth slot) of the random cases


def _random_case(seed, n_truth=3, n_slots=3, d=4):
    """Truths with random birth/death gaps; estimates near random truths with labels from ``POOL``."""
    rng = np.random.default_rng(seed)
    truth = rng.normal(scale=80.0, size=(K, n_truth, d))
    alive = rng.random((K, n_truth)) < 0.65
    truth[~alive] = 0.0
    est = rng.normal(scale=80.0, size=(K, n_slots, d))  # garbage where absent
    labels = np.full((K, n_slots, 2), -1)
    mask = rng.random((K, n_slots)) < 0.7
    for k in range(K):
        pick = rng.permutation(len(POOL))[:n_slots]  # distinct labels within the scan
        for e in range(n_slots):
            if mask[k, e]:
                labels[k, e] = POOL[pick[e]]
                est[k, e] = truth[k, rng.integers(n_truth)] + rng.normal(scale=40.0, size=d)
    return truth, alive, est, labels, mask


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("p", [1, 2])
@pytest.mark.parametrize("window", [3, K])
def test_ospa2_matches_brute_force(seed, p, window):
    case = _random_case(seed)
    got = ospa2(*case, cutoff=100.0, order=p, window=window)
    want = ospa2_ref(*case, c=100.0, p=p, window=window)
    assert got.shape == (K,)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_ospa2_matches_brute_force_other_dims_and_sizes():
    for seed, (n_truth, n_slots) in enumerate([(1, 3), (3, 1), (2, 2), (3, 3)]):
        case = _random_case(100 + seed, n_truth=n_truth, n_slots=n_slots)
        got = ospa2(*case, cutoff=60.0, order=1.5, window=2, position_dims=(2, 0))
        want = ospa2_ref(*case, c=60.0, p=1.5, window=2, position_dims=(2, 0))
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def _two_targets(K=10):
    """Two well separated straight tracks, alive throughout."""
    t = np.arange(K, dtype=float)
    truth = np.zeros((K, 2, 4))
    truth[:, 0, 0], truth[:, 0, 2] = 10.0 * t, 10.0
    truth[:, 1, 0], truth[:, 1, 1], truth[:, 1, 2] = 10.0 * t, 500.0, 10.0
    return truth, np.ones((K, 2), bool)


def test_identical_estimates_give_zero():
    truth, alive, *_ = _random_case(7)
    # the same positions under one label per target, in shuffled slots, with garbage in empty slots
    rng = np.random.default_rng(0)
    N = truth.shape[1]
    est = np.full_like(truth, np.nan)
    labels = np.full((K, N, 2), -1)
    mask = np.zeros((K, N), bool)
    for k in range(K):
        slots = rng.permutation(N)
        est[k, slots] = np.where(alive[k][:, None], truth[k], np.nan)
        labels[k, slots] = np.stack([np.full(N, 1), np.arange(N)], -1)
        mask[k, slots] = alive[k]
    for p, window in [(1, 3), (2, K)]:
        np.testing.assert_array_equal(ospa2(truth, alive, est, labels, mask, order=p, window=window), 0.0)
    sw = label_switches(truth, alive, est, labels, mask)
    assert sw.total == 0


def test_empty_estimates_give_cutoff_where_truth_exists():
    K_, c = 10, 40.0
    truth = np.zeros((K_, 1, 2))
    alive = np.zeros((K_, 1), bool)
    alive[3:6, 0] = True  # scans 3, 4, 5
    E = 2
    est, labels, mask = np.zeros((K_, E, 2)), np.full((K_, E, 2), -1), np.zeros((K_, E), bool)
    got = ospa2(truth, alive, est, labels, mask, cutoff=c, window=2)
    want = np.where((np.arange(K_) >= 3) & (np.arange(K_) <= 6), c, 0.0)  # the window [k-1, k] meets 3..5
    np.testing.assert_array_equal(got, want)
    # no estimate slots at all, and no truths at all
    np.testing.assert_array_equal(
        ospa2(
            truth,
            alive,
            np.zeros((K_, 0, 2)),
            np.zeros((K_, 0, 2), int),
            np.zeros((K_, 0), bool),
            cutoff=c,
            window=2,
        ),
        want,
    )
    np.testing.assert_array_equal(
        ospa2(np.zeros((K_, 0, 2)), np.zeros((K_, 0), bool), est, labels, mask, cutoff=c), 0.0
    )


@pytest.mark.parametrize("p", [1, 2])
def test_constant_offset_gives_the_offset(p):
    truth, alive = _two_targets()
    truth, alive = truth[:, :1], alive[:, :1]
    delta = 3.0
    est = truth + np.array([0.6, 0.8, 0.0, 0.0]) * delta  # |offset| = delta in position, velocity untouched
    labels = np.broadcast_to(np.array([4, 0]), (10, 1, 2))
    got = ospa2(truth, alive, est, labels, alive, cutoff=100.0, order=p, window=4)
    np.testing.assert_allclose(got, delta, rtol=1e-12)


def _swap_case(swap, K=10):
    truth, alive = _two_targets(K)
    est = truth.copy()
    labels = np.zeros((K, 2, 2), int)
    labels[:, 0] = [0, 0]
    labels[:, 1] = [0, 1]
    if swap:  # from scan K/2 on, label (0, 0) follows target 1 and label (0, 1) target 0
        labels[K // 2 :] = labels[K // 2 :, ::-1]
    return truth, alive, est, labels, alive.copy()


def test_label_swap_raises_ospa2_and_counts_two_switches():
    c = 100.0
    case = _swap_case(True)
    got = ospa2(*case, cutoff=c, order=1, window=10)
    # positions match at every scan, but from scan 5 on each label track is half on one target
    # and half on the other: d = (5 * 0 + (k - 4) * c) / (k + 1) for both pairs of the best assignment
    k = np.arange(10)
    np.testing.assert_allclose(got, np.where(k < 5, 0.0, c * (k - 4) / (k + 1)), rtol=1e-12)
    assert got[-1] == pytest.approx(c / 2)
    np.testing.assert_allclose(got, ospa2_ref(*case, c=c, p=1, window=10), rtol=1e-12)
    # a short window forgets the swap once it has slid past it
    short = ospa2(*case, cutoff=c, window=3)
    assert short[4] == 0.0 and short[5] > 0 and short[6] > 0 and short[7] == 0.0

    sw = label_switches(*case, gate=20.0)
    assert isinstance(sw, LabelSwitches)
    assert sw.total == 2
    np.testing.assert_array_equal(sw.per_target, [1, 1])
    np.testing.assert_array_equal(sw.fragmentations, [0, 0])
    np.testing.assert_array_equal(sw.labels, [[0, 0], [0, 1]])
    np.testing.assert_array_equal(sw.assigned[:5], [[0, 1]] * 5)
    np.testing.assert_array_equal(sw.assigned[5:], [[1, 0]] * 5)


def test_no_swap_no_switch():
    case = _swap_case(False)
    np.testing.assert_array_equal(ospa2(*case, window=10), 0.0)
    sw = label_switches(*case, gate=20.0)
    assert sw.total == 0
    np.testing.assert_array_equal(sw.per_target, [0, 0])


def test_label_switches_gate_gaps_and_fragmentations():
    truth, alive = _two_targets(8)
    est = truth.copy()
    labels = np.zeros((8, 2, 2), int)
    labels[:, 0], labels[:, 1] = [1, 0], [1, 1]
    mask = np.ones((8, 2), bool)
    mask[2:4, 0] = False  # target 0 not estimated at scans 2, 3: an interruption, the same label after
    est[5, 1, 0] += 50.0  # target 1's estimate outside the gate at scan 5
    labels[6:, 1] = [7, 0]  # then target 1 is picked up by a new label: one switch
    sw = label_switches(truth, alive, est, labels, mask, gate=20.0)
    np.testing.assert_array_equal(sw.per_target, [0, 1])
    np.testing.assert_array_equal(sw.fragmentations, [1, 1])
    assert sw.total == 1
    assert (sw.assigned[2:4, 0] == -1).all() and sw.assigned[5, 1] == -1
    # a target that dies and comes back is not interrupted while dead
    alive2 = alive.copy()
    alive2[2:4, 0] = False
    sw2 = label_switches(truth, alive2, est, labels, mask, gate=20.0)
    np.testing.assert_array_equal(sw2.fragmentations, [0, 1])


def test_far_estimate_does_not_break_a_gated_pair():
    # truths at 0 and 10, estimates at 4 and -100 (1-D positions): raw distances would pair 0 with -100
    truth = np.array([[[0.0], [10.0]]])
    est = np.array([[[4.0], [-100.0]]])
    labels = np.array([[[0, 0], [0, 1]]])
    sw = label_switches(
        truth, np.ones((1, 2), bool), est, labels, np.ones((1, 2), bool), gate=5.0, position_dims=(0,)
    )
    np.testing.assert_array_equal(sw.assigned, [[0, -1]])


def test_errors_name_the_argument():
    case = list(_swap_case(True))
    truth, alive, est, labels, mask = case
    bad = [
        (dict(truth_states=truth[0]), "truth_states"),
        (dict(truth_alive=alive[:, :1]), "truth_alive"),
        (dict(est_states=est[:-1]), "est_states"),
        (dict(est_states=est[..., :3]), "est_states"),
        (dict(est_labels=labels[..., :1]), "est_labels"),
        (dict(est_labels=labels.astype(float)), "est_labels"),
        (dict(est_mask=mask[:, :1]), "est_mask"),
    ]
    names = ["truth_states", "truth_alive", "est_states", "est_labels", "est_mask"]
    for change, name in bad:
        args = dict(zip(names, case)) | change
        for fn in (ospa2, label_switches):
            with pytest.raises(ValueError, match=name):
                fn(**args)
    for kw, name in [
        (dict(cutoff=0.0), "cutoff"),
        (dict(cutoff=-1.0), "cutoff"),
        (dict(cutoff=np.inf), "cutoff"),
        (dict(order=0.5), "order"),
        (dict(window=0), "window"),
        (dict(window=2.5), "window"),
        (dict(position_dims=(0, 4)), "position_dims"),
        (dict(position_dims=()), "position_dims"),
    ]:
        with pytest.raises(ValueError, match=name):
            ospa2(*case, **kw)
    with pytest.raises(ValueError, match="gate"):
        label_switches(*case, gate=0.0)


def test_label_twice_in_a_scan_and_present_empty_label_are_errors():
    truth, alive, est, labels, mask = _swap_case(False)
    dup = labels.copy()
    dup[3, 1] = dup[3, 0]
    with pytest.raises(ValueError, match="scan 3"):
        ospa2(truth, alive, est, dup, mask)
    with pytest.raises(ValueError, match="scan 3"):
        label_switches(truth, alive, est, dup, mask)
    # the duplicate is fine where one of the two is absent
    m = mask.copy()
    m[3, 1] = False
    ospa2(truth, alive, est, dup, m)
    empty = labels.copy()
    empty[4, 0] = -1
    with pytest.raises(ValueError, match="empty label"):
        ospa2(truth, alive, est, empty, mask)
