"""gmjax.reduction.eise.relaxed: the relaxed EISE from the grid's sums against its definition, its
hand-written slopes against forward mode, gradients, the distinct-pair evaluation, and batch independence."""

import importlib
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax.reduction.eise import (
    eise,
    hard_eise,
    merge_membership,
    relaxed_eise,
    relaxed_membership,
)

# the search's parts, by module (the package `gmjax.reduction` exports a function named `eise`)
eise_relaxed = importlib.import_module("gmjax.reduction.eise.relaxed")
eise_newton = importlib.import_module("gmjax.reduction.eise.newton")

from eise_cases import K, _grid_for, case, random_gm


def _dense_relaxed_eise(lam, gm, grid, labels, counts, temperature, alpha, method):
    """The relaxation by its definition: soft memberships, their merge, the closed-form EISE."""
    A, pi = relaxed_membership(lam, grid, labels, temperature)
    merged = merge_membership(gm, A, method)
    n_soft = jnp.sum(pi * counts.astype(pi.dtype))
    n_ref = jnp.sum(gm.mask.astype(jnp.int32))
    return eise(gm, A, merged, n_soft, n_ref, alpha=alpha, clip=False)


@pytest.mark.parametrize(
    ("d", "method"),
    [
        (d, method)
        if (d, method) not in {(3, "ci"), (4, "ci"), (4, "moment")}
        else pytest.param(d, method, marks=pytest.mark.slow)  # compiling; d = 2 has the same code paths
        for d in (1, 2, 3, 4)
        for method in ("ci", "moment")
    ],
)
def test_relaxed_eise_from_grid_sums_equals_its_definition(d, method):
    """``relaxed_eise`` works from per-grid-point sums (eise.relaxed._RelaxedParts); value and derivatives
    equal the soft clusters merged and integrated directly, padding included."""
    gm, *_ = random_gm(3 + d, n=9, d=d)
    grid, labels, counts = _grid_for(gm)

    def fast(lam):
        return relaxed_eise(lam, gm, grid, labels, counts, temperature=0.2, alpha=0.01, method=method)

    def dense(lam):
        return _dense_relaxed_eise(lam, gm, grid, labels, counts, 0.2, 0.01, method)

    def derivatives(f):  # forward over forward (as the Newton search takes them; compiles fastest)
        def slope(lam):
            return jax.jvp(f, (lam,), (jnp.ones_like(lam),))[1]

        return jax.jit(jax.vmap(lambda lam: (f(lam), *jax.jvp(slope, (lam,), (jnp.ones_like(lam),)))))

    lams = jnp.array([1.05, 1.5, 2.33, 2.9])
    (f_fast, g_fast, h_fast), (f_dense, g_dense, h_dense) = derivatives(fast)(lams), derivatives(dense)(lams)
    np.testing.assert_allclose(f_fast, f_dense, rtol=1e-13)
    scale = 1e-12 * float(jnp.max(jnp.abs(f_dense)))
    np.testing.assert_allclose(g_fast, g_dense, rtol=1e-9, atol=scale)
    np.testing.assert_allclose(h_fast, h_dense, rtol=1e-9, atol=scale)


@pytest.mark.parametrize(
    ("d", "method", "regularizer"),
    [  # each d and each method by default; the other two (20-35 s of compiling each) are slow
        (3, "ci", "exp"),
        (1, "moment", "log10"),
        pytest.param(1, "ci", "exp", marks=pytest.mark.slow),
        pytest.param(3, "moment", "log10", marks=pytest.mark.slow),
    ],
)
def test_newton_slopes_by_hand_equal_forward_mode(d, method, regularizer):
    """Newton's derivatives of the relaxed EISE, derived by hand
    (``eise.relaxed._relaxed_value_and_slopes``), equal forward-over-forward ``jvp`` of its value, and the
    value they come with equals the value, padding included; float32 to its precision."""
    options = dict(method=method, regularizer=regularizer, ise_scale=0.5)
    fun = partial(eise_relaxed._relaxed_at, **options)
    by_hand = partial(eise_relaxed._relaxed_value_and_slopes, **options)
    lams = jnp.array([0.7, 1.05, 1.5, 2.0, 2.33, 2.9])  # off, between and on grid points
    # compiled once, for both seeds: the relaxation's parts are arguments
    value, jvp_slopes, hand_slopes = (
        jax.jit(jax.vmap(f, in_axes=(0, None))) for f in (fun, partial(eise_newton._jvp_slopes, fun), by_hand)
    )

    relaxed_parts = jax.jit(eise_relaxed._relaxed_parts, static_argnums=4)  # (eager: op by op)

    def evaluate(dtype, seed):
        gm, *_ = random_gm(seed, n=9, d=d, dtype=dtype)
        grid, labels, counts = _grid_for(gm)
        parts = relaxed_parts(gm, grid.astype(dtype), labels, counts, method)
        args = (parts, jnp.asarray(0.2, dtype), jnp.asarray(0.01, dtype))
        at = lambda f: f(lams.astype(dtype), args)  # noqa: E731
        return at(value), at(jvp_slopes), at(hand_slopes)

    steepest = 0.0
    for seed in (3 + d, 11):
        f, jvp, hand = evaluate(jnp.float64, seed)
        scale = float(np.max(np.abs(f)))  # where all grid clusterings agree the slopes are rounding
        steepest = max(steepest, float(np.max(np.abs(jvp[1]))) / scale)
        np.testing.assert_allclose(hand[0], f, rtol=1e-12)  # the value, by its own formula
        np.testing.assert_allclose(jvp[0], f, rtol=1e-14)
        for exact, ours in zip(jvp, hand):
            np.testing.assert_allclose(ours, exact, rtol=1e-9, atol=1e-12 * scale)
        f32, _, hand32 = evaluate(jnp.float32, seed)  # (float32 jvp can be NaN where these are not)
        np.testing.assert_allclose(hand32[0], f32, rtol=1e-5)
        for exact, ours in zip(jvp, hand32):
            assert ours.dtype == jnp.float32
            np.testing.assert_allclose(ours, exact, rtol=1e-3, atol=1e-4 * scale)
    assert steepest > 1e-3  # not only flat relaxations


@pytest.mark.parametrize("capacity", [K, 40])
def test_relaxed_parts_hh_equals_the_one_hot_products(capacity):
    """The relaxation's ``(G, G)`` matrix ``hh[g, h] = Σ_c (A_g w)_cᵀ S (A_h w)_c``, summed member by
    member (unrolled up to 32 slots, a ``fori_loop`` above), equals the one-hot products in NumPy,
    padding included."""
    gm = random_gm(3, n=capacity - 3, d=2, capacity=capacity)[0]
    grid, labels, counts = _grid_for(gm)
    parts = jax.jit(lambda gm: eise_relaxed._relaxed_parts(gm, grid, labels, counts, "ci"))(gm)
    w = np.where(gm.mask, gm.weights, 0.0)
    S = np.asarray(eise_relaxed.self_overlaps(gm))
    live_labels = np.where(np.asarray(gm.mask)[None], np.asarray(labels), -1)
    A = [(lab[:, None] == np.arange(capacity)) * w[:, None] for lab in live_labels]  # (K, C) each
    expected = np.array([[np.sum(a * (S @ b)) for b in A] for a in A])
    np.testing.assert_allclose(parts.hh, expected, rtol=1e-14, atol=1e-15 * np.max(expected))


def test_relaxed_eise_gradient_matches_finite_differences():
    gm = case("multimodal")
    grid, labels, counts = _grid_for(gm)

    @jax.jit
    def f(lam):
        return relaxed_eise(lam, gm, grid, labels, counts, temperature=0.2, alpha=0.01)

    g = jax.jit(jax.grad(f))
    h = jax.jit(jax.grad(jax.grad(f)))
    hess = jax.jit(jax.hessian(f))
    for lam in (1.15, 1.5, 2.05, 2.7):
        eps = 1e-5
        fd = (f(lam + eps) - f(lam - eps)) / (2 * eps)
        assert float(g(lam)) == pytest.approx(float(fd), rel=1e-6, abs=1e-10)
        fd2 = (g(lam + eps) - g(lam - eps)) / (2 * eps)
        assert float(h(lam)) == pytest.approx(float(fd2), rel=1e-5, abs=1e-8)
        assert float(h(lam)) == pytest.approx(float(hess(lam)), rel=1e-12)
    # the relaxation is not flat where the hard EISE is (piecewise constant)
    assert any(abs(float(g(lam))) > 1e-6 for lam in (1.15, 1.5, 2.05, 2.7))


def test_relaxation_tends_to_hard_eise_at_grid_points():
    gm = case("bimodal")
    grid, labels, counts = _grid_for(gm)
    soft_fn = jax.jit(lambda lam: relaxed_eise(lam, gm, grid, labels, counts, temperature=1e-3, alpha=0.01))
    for k in (0, 4, 10):
        hard, _, _ = hard_eise(gm, labels[k], alpha=0.01)
        soft = soft_fn(grid[k])
        assert float(soft) == pytest.approx(float(hard), rel=1e-9)


def test_distinct_pairs_match_a_loop_alone_and_under_vmap():
    """``J_hr``'s distinct (component, cluster) pairs, listed by component then first grid point,
    with every live ``(g, m)`` pointing at its own and their count; under vmap each run's own."""
    rng = np.random.default_rng(0)
    G = 11
    few = np.tile(rng.integers(0, 3, K), (G, 1))  # every grid point alike: one pair per component
    few[6:, :4] = 5
    many = (np.arange(G)[:, None] + rng.integers(0, K, K)) % K  # every pair distinct
    many[:, -2:] = -1  # padding
    counts = []
    for labels in (few, many):
        pairs = jax.jit(eise_relaxed._distinct_pairs)(jnp.asarray(labels))
        expected = []
        for m in range(K):
            for g in range(G):
                if labels[g, m] >= 0 and (m, labels[g, m]) not in expected:
                    expected.append((m, labels[g, m]))
        n = len(expected)
        member, cluster, of = (np.asarray(a) for a in pairs[:3])
        assert list(zip(member[:n].tolist(), cluster[:n].tolist())) == expected
        assert not np.any(member[n:]) and not np.any(cluster[n:])
        for g, m in np.argwhere(labels >= 0):
            assert (member[of[g, m]], cluster[of[g, m]]) == (m, labels[g, m])
        assert int(pairs.n_distinct) == n
        counts.append(n)
    assert counts == [K + 4, G * (K - 2)]
    batched = jax.vmap(eise_relaxed._distinct_pairs)(jnp.asarray(np.stack([few, many])))
    np.testing.assert_array_equal(batched.n_distinct, counts)


def _relaxed_problems_2d(method):
    """2-D relaxations: clusterings on the grid, and random labels with nearly every pair distinct."""
    problems = []
    for seed in range(4):
        gm = random_gm(seed, n=10, d=2)[0]
        grid, labels, counts = _grid_for(gm)
        if seed == 3:  # every pair of the 10 components distinct
            shift = np.random.default_rng(seed).integers(0, 10, labels.shape[1])
            labels = jnp.asarray((np.arange(labels.shape[0])[:, None] + shift) % 10)
        problems.append((gm, grid, labels, counts))
    return problems


@pytest.mark.parametrize("method", ["ci", pytest.param("moment", marks=pytest.mark.slow)])  # 40 s compiling
def test_relaxation_over_distinct_pairs_is_the_full_one(method):
    """For d >= 2 the search evaluates ``J_hr`` once per distinct pair, in chunks: value and slopes
    equal those over all ``G K`` pairs, alone (runs that need one chunk and runs that need four)
    and under vmap (the batch's pairs side by side: several chunks, a run's pairs split across
    two), and (``"ci"``) under a vmap of vmaps. The same arithmetic on the same inputs, but XLA
    fuses the programs differently: here a few ulps apart in the slopes (on the benchmark's
    captured 4-D searches every result was bit-identical)."""
    options = dict(method=method, regularizer="exp", ise_scale=0.5)
    value = partial(eise_relaxed._relaxed_at, **options)
    slopes = partial(eise_relaxed._relaxed_value_and_slopes, **options)

    def evaluate(distinct_pairs, gm, grid, labels, counts, lam):
        parts = eise_relaxed._relaxed_parts(gm, grid, labels, counts, method, distinct_pairs=distinct_pairs)
        assert (parts.pairs is None) != distinct_pairs
        args = (parts, jnp.asarray(0.2), jnp.asarray(0.01))
        return value(lam, args), *slopes(lam, args)

    problems = _relaxed_problems_2d(method)
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *problems)
    lams = jnp.asarray([1.3, 1.9, 2.45, 2.0])
    counts = np.asarray(jax.vmap(lambda labels: eise_relaxed._distinct_pairs(labels).n_distinct)(stacked[2]))
    n_pairs = stacked[2].shape[1] * stacked[2].shape[2]
    alone_chunk = eise_relaxed._pair_chunk(n_pairs)
    assert -(-counts.min() // alone_chunk) == 1 and -(-counts[-1] // alone_chunk) == 4
    size = eise_relaxed._distinct_pairs(stacked[2][0]).member.size
    batch_chunk = eise_relaxed._pair_chunk(n_pairs, len(counts))
    ends = np.cumsum(counts)
    split = (ends - counts) // batch_chunk != (ends - 1) // batch_chunk  # a run's pairs in two chunks
    assert counts.sum() > 3 * batch_chunk and np.any(split) and size >= n_pairs
    over_pairs, over_all = (jax.jit(jax.vmap(partial(evaluate, b)))(*stacked, lams) for b in (True, False))
    for a, b in zip(over_pairs, over_all):
        assert np.all(np.isfinite(b))
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14 * float(np.max(np.abs(b))))
    alone_fns = [jax.jit(partial(evaluate, b)) for b in (True, False)]  # compiled once for the four
    for k, problem in enumerate(problems):  # alone: as many chunks as this run needs
        alone = (fn(*problem, lams[k]) for fn in alone_fns)
        for a, b in zip(*alone):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14 * float(np.max(np.abs(b))))
    if method == "ci":  # a vmap of vmaps (the inner batch rule, batched again): two runs of two
        twice = jax.tree_util.tree_map(lambda a: a.reshape((2, 2) + a.shape[1:]), (*stacked, lams))
        nested = jax.jit(jax.vmap(jax.vmap(partial(evaluate, True))))(*twice)
        for a, b in zip(nested, over_all):
            np.testing.assert_allclose(
                a.reshape(b.shape), b, rtol=1e-12, atol=1e-14 * float(np.max(np.abs(b)))
            )


@pytest.mark.parametrize("d, method", [(1, "ci"), (3, "moment")])
def test_relaxed_slopes_do_not_depend_on_the_batch(d, method):
    """Under vmap Newton halves in blocks of ``_HALVING_BLOCK`` runs gathered from its batch, so a
    run's relaxed value and slopes must be bitwise the same in a block as in the whole batch, here
    600 runs: large enough that XLA:CPU hands plain reductions and dots to other kernels."""
    n_runs, block = 600, eise_newton._HALVING_BLOCK
    rng = np.random.default_rng(3)
    gms = [random_gm(s, n=int(rng.integers(4, K + 1)), d=d)[0] for s in range(n_runs)]
    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gms)

    def parts_of(gm):
        return eise_relaxed._relaxed_parts(gm, *_grid_for(gm), method, distinct_pairs=True)

    parts = jax.jit(jax.vmap(parts_of))(batch)
    lam = jnp.asarray(rng.uniform(1.0, 3.0, n_runs))
    slopes = partial(eise_relaxed._relaxed_value_and_slopes, method=method, regularizer="exp", ise_scale=0.5)
    evaluate = jax.jit(jax.vmap(lambda p, l: slopes(l, (p, jnp.asarray(0.2), jnp.asarray(0.01)))))
    whole = evaluate(parts, lam)
    assert all(np.all(np.isfinite(a)) for a in whole)
    for start in (0, 100):
        rows = slice(start, start + block)
        in_block = evaluate(jax.tree_util.tree_map(lambda a: a[rows], parts), lam[rows])
        for a, b in zip(in_block, whole):
            np.testing.assert_array_equal(a, b[rows])
