"""gmjax.reduction.eise.search: the confidence search (grid and Newton) against the NumPy reference, its
batching (vmap == alone), ties, and gradients."""

import importlib
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax.mixture import GaussianMixture
from gmjax.reduction.clustering import gauss_cluster
from gmjax.reduction.eise import (
    ConfidenceSearch,
    EISECriterion,
    hard_eise,
    search_confidence,
)
from gmjax.reduction.pcm import pcm
from references import pcm_numpy as ref

# the search's parts, by module (the package `gmjax.reduction` exports a function named `eise`)
eise_search = importlib.import_module("gmjax.reduction.eise.search")

from eise_cases import CASES, NEWTON_TOL, K, case, case_np, random_gm


@pytest.mark.parametrize("name", list(CASES))
def test_newton_no_worse_than_grid_on_static_cases(name):
    gm = case(name)
    res = search_confidence(gm, ConfidenceSearch(alpha=0.01))
    assert bool(jnp.isfinite(res.lam_newton)) and 1.0 <= float(res.lam_newton) <= 3.0
    assert int(res.iterations) >= 1
    assert float(res.eise_newton) <= float(res.eise_grid) * (1 + NEWTON_TOL)
    assert float(res.eise) <= float(res.eise_grid) * (1 + NEWTON_TOL)
    assert float(res.eise_grid) == pytest.approx(float(jnp.min(res.grid_eise)))
    # the chosen result is consistent with a hard clustering at the chosen lambda
    labels = gauss_cluster(gm, res.lam).labels
    np.testing.assert_array_equal(labels, res.labels)


def _search_2d(gm, alpha=0.01):
    return search_confidence(gm, ConfidenceSearch(alpha=alpha))  # [1, 3], 11 points, 8 Newton steps


def _search_2d_lam_slope(derivative):
    """``d λ_newton / d α`` of a 2-D search by ``derivative`` (forward or reverse mode) and by a
    central finite difference."""
    gm = random_gm(1, n=10, d=2)[0]
    lam_newton = jax.jit(lambda a: _search_2d(gm, a).lam_newton)
    slope = jax.jit(derivative(lambda a: _search_2d(gm, a).lam_newton))(0.01)
    h = 1e-5
    return slope, (lam_newton(0.01 + h) - lam_newton(0.01 - h)) / (2 * h)


@pytest.mark.slow  # a minute of compiling; 1-D: test_pcm_jit_eager_vmap_padding_and_dtypes_grid_search
def test_search_in_2d_jit_eager_vmap_float32_and_derivative():
    """The 2-D search (distinct pairs): jit == eager, vmap == loop, float32 near float64, and the
    forward-mode derivative of its ``λ`` through Newton (the custom JVP's scan runs over all pairs)
    equals finite differences; reverse mode: the test below."""
    gms = [random_gm(s, n=10, d=2)[0] for s in range(4)]
    eager = [_search_2d(g) for g in gms]
    assert any(int(r.iterations) > 1 for r in eager)
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gms)
    batched = jax.jit(jax.vmap(_search_2d))(stacked)
    for k, r in enumerate(eager):
        for a, b in zip(jax.tree_util.tree_leaves(r), jax.tree_util.tree_leaves(batched)):
            if jnp.issubdtype(a.dtype, jnp.floating):  # batched arithmetic rounds differently
                np.testing.assert_allclose(a, b[k], rtol=1e-12, atol=1e-14)
            else:
                np.testing.assert_array_equal(a, b[k])
    g32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, gms[0])
    r32 = _search_2d(g32)
    assert r32.lam_newton.dtype == jnp.float32
    np.testing.assert_allclose(r32.lam_newton, eager[0].lam_newton, rtol=1e-4)
    np.testing.assert_array_equal(r32.labels, eager[0].labels)

    forward = lambda f: lambda a: jax.jvp(f, (a,), (jnp.ones_like(a),))[1]  # noqa: E731
    slope, fd = _search_2d_lam_slope(forward)
    assert np.isfinite(slope) and slope != 0.0
    np.testing.assert_allclose(slope, fd, rtol=1e-4)


@pytest.mark.slow  # 75 s of compiling; the default suite's twin is the 1-D test below
def test_search_in_2d_gradient_matches_finite_differences():
    """``jax.grad`` of the 2-D search's ``λ`` (the transpose of the custom JVP, pairs dropped) equals
    a central finite difference."""
    slope, fd = _search_2d_lam_slope(jax.grad)
    assert np.isfinite(slope) and slope != 0.0
    np.testing.assert_allclose(slope, fd, rtol=1e-4)


def test_search_in_1d_gradient_matches_finite_differences():
    """The default suite's reverse-mode check through Newton: ``jax.grad`` of a 1-D search's ``λ``
    (the transpose of the custom JVP) equals a central finite difference."""
    gm = random_gm(1, n=10, d=1)[0]
    lam_newton = jax.jit(lambda a: search_confidence(gm, ConfidenceSearch(alpha=a)).lam_newton)
    slope = jax.jit(jax.grad(lambda a: search_confidence(gm, ConfidenceSearch(alpha=a)).lam_newton))(0.01)
    h = 1e-5
    fd = (lam_newton(0.01 + h) - lam_newton(0.01 - h)) / (2 * h)
    assert np.isfinite(slope) and slope != 0.0
    np.testing.assert_allclose(slope, fd, rtol=1e-4)


@pytest.mark.parametrize("criterion", [EISECriterion.seed000(), EISECriterion.seed003()])
def test_grid_costs_each_run_once_under_vmap(criterion):
    """Under ``vmap`` the grid search costs only the first clustering of each run of equal
    consecutive clusterings (``search._grid_costs``), the run starts of the whole batch in blocks of
    64 (here 24 mixtures, more run starts than one block). Every grid point's EISE and N' equal the
    search alone (which costs every grid point) and the hard EISE of that grid point's clustering."""
    d = 2
    batch = [random_gm(seed, n=10, d=d)[0] for seed in range(24)]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *batch)
    search = ConfidenceSearch(alpha=0.01, grid_size=15, newton_steps=0, criterion=criterion)
    res_v = jax.jit(jax.vmap(lambda g: search_confidence(g, search)))(stacked)
    starts = 0
    for b, gm in enumerate(batch):
        res = search_confidence(gm, search)
        if criterion.method == "ci":  # the hard CI merge sums members one by one: the same bits
            np.testing.assert_array_equal(np.asarray(res_v.grid_eise[b]), np.asarray(res.grid_eise))
        else:  # the moment merge's one-hot products are dots, summed in an order XLA picks by shape,
            # and J_hh - 2 J_hr + J_rr cancels: equal to the references' 1e-12
            np.testing.assert_allclose(np.asarray(res_v.grid_eise[b]), np.asarray(res.grid_eise), rtol=1e-12)
        np.testing.assert_array_equal(np.asarray(res_v.grid_counts[b]), np.asarray(res.grid_counts))
        labels = gauss_cluster(
            gm, res.grid, triangular=criterion.triangular, subset_rule=criterion.subset_rule
        ).labels
        starts += 1 + int(jnp.sum(jnp.any(labels[1:] != labels[:-1], axis=-1)))
        for g in range(search.grid_size):
            value, _, n = hard_eise(
                gm,
                labels[g],
                alpha=0.01,
                method=criterion.method,
                regularizer=criterion.regularizer,
                ise_scale=criterion.ise_scale,
            )
            np.testing.assert_allclose(float(res.grid_eise[g]), float(value), rtol=1e-13)
            assert int(res.grid_counts[g]) == int(n)
    assert starts > 64  # the batch rule ran more than one block


def test_search_under_vmap_over_no_runs():
    """Both batch rules (the clustering at Newton's λ, the batch's pairs side by side) take an empty
    batch."""
    gm = random_gm(0, n=10, d=2)[0]
    none = jax.tree_util.tree_map(lambda a: jnp.stack([a])[:0], gm)
    res = jax.vmap(lambda g: search_confidence(g, ConfidenceSearch(alpha=0.01)))(none)
    assert res.lam.shape == (0,) and res.labels.shape == (0, K)


def test_clustering_unless_known_skips_the_known_runs_alone_and_under_vmap():
    """Newton's clustering is computed only for the runs whose judgment matrix matches no grid
    point's: alone through a ``cond``, under vmap by gathering the runs that need it into blocks
    (here 3 blocks of 16, the last one part known runs and part padding). Known runs get the labels
    given, even wrong ones; the others get exactly the clustering's labels."""
    gms = [random_gm(s, n=8 + s % 4)[0] for s in range(40)]
    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gms)
    lam = jnp.linspace(1.0, 3.0, 40)
    known = jnp.asarray(np.random.default_rng(0).uniform(size=40) < 0.15)
    wrong = jnp.full((40, K), 7, jnp.int32)  # not a clustering: shows which runs were skipped

    def cluster(gm, lam):
        return gauss_cluster(gm, lam).labels

    def labels(known, known_labels, gm, lam):
        return eise_search._cluster_unless_known(cluster, known, known_labels, gm, lam)

    fresh = jax.vmap(cluster)(batch, lam)
    expected = np.where(np.asarray(known)[:, None], 7, np.asarray(fresh))
    np.testing.assert_array_equal(jax.jit(jax.vmap(labels))(known, wrong, batch, lam), expected)
    for i in (0, 1, 2, 3):  # alone
        one = jax.tree_util.tree_map(lambda a: a[i], batch)
        np.testing.assert_array_equal(jax.jit(labels)(known[i], wrong[i], one, lam[i]), expected[i])
    assert 2 * eise_search._CLUSTER_BLOCK < int(jnp.sum(~known)) < 40  # three blocks, some known


def test_search_newton_clustering_is_the_clustering_at_its_lambda():
    """Where the search keeps Newton's λ, its labels (reused from a grid point with the same
    judgment matrix, or clustered afresh) are those of clustering at that λ, under vmap."""
    gms = [random_gm(s, n=10)[0] for s in range(24)] + [case(name) for name in CASES]
    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gms)
    res = jax.jit(jax.vmap(lambda g: search_confidence(g, ConfidenceSearch(alpha=0.01))))(batch)
    fresh = jax.vmap(lambda g, lam: gauss_cluster(g, lam).labels)(batch, res.lam)
    np.testing.assert_array_equal(res.labels, fresh)
    assert int(jnp.sum(~res.used_fallback)) > 0 and bool(jnp.any(res.lam != res.lam_grid))


def test_search_grid_matches_numpy_reference():
    w, m, P = case_np("multimodal")
    gm = case("multimodal")
    res = search_confidence(gm, ConfidenceSearch(newton_steps=0, alpha=0.001))
    lam_ref, (_, _, _, _, e_ref) = ref.pcm_grid(w, m, P, prune=False, grid=11)
    assert float(res.lam) == pytest.approx(lam_ref)
    assert float(res.eise) == pytest.approx(e_ref, rel=1e-10)
    assert bool(res.used_fallback)


def test_grid_ties_pick_the_first_lambda_alone_and_under_vmap():
    """Two grid points that give the same partition under other head rows have the same EISE up to
    the summation order; the search keeps the first (smallest ``λ``), as exact arithmetic and the
    numba loop do, so a mixture gets the same ``λ`` alone and under vmap. Mixtures 139 and 968 of
    ``bench_reducer_limit``'s 1-D draw are such ties (a plain ``argmin`` gave ``λ = 3.0`` under vmap
    for both, 1.8 and 2.6 alone)."""
    from references import pcm_numba

    rng = np.random.default_rng(46)  # bench_reducer_limit.draw(rng, 1000, 60, 1)
    B, K = 1000, 60
    w = rng.uniform(1e-2, 0.2, (B, K))
    w /= w.sum(1, keepdims=True)
    m = rng.uniform(-2.0, 4.0, (B, K, 1))
    q, _ = np.linalg.qr(rng.normal(size=(B, K, 1, 1)))
    s2 = rng.uniform(0.4, 1.0, (B, K, 1)) ** 2
    P = np.einsum("bkij,bkj,bklj->bkil", q, s2, q)
    pick = [139, 968, 0]  # two ties and an ordinary mixture
    w, m, P = w[pick], m[pick], 0.5 * (P[pick] + np.swapaxes(P[pick], -1, -2))
    gms = GaussianMixture(jnp.asarray(w), jnp.asarray(m), jnp.asarray(P), jnp.ones(w.shape, bool))
    reduce = partial(pcm, max_components=20, capacity=20, newton_steps=0)
    _, batched = jax.jit(jax.vmap(reduce))(gms)
    for b in range(len(pick)):
        _, alone = jax.jit(reduce)(jax.tree_util.tree_map(lambda a: a[b], gms))
        loop = pcm_numba.pcm.py_func(w[b], m[b], P[b], 20, 20)
        assert float(alone.aux["lambda"]) == float(batched.aux["lambda"][b]) == loop[5]
        np.testing.assert_array_equal(alone.labels, batched.labels[b])
    assert [float(x) for x in batched.aux["lambda"][:2]] == [1.8, 2.6]


def test_first_minimiser_keeps_the_first_of_values_equal_to_rounding():
    first = eise_search._first_minimiser
    values = jnp.asarray([3.0, 1.0 + 4e-16, 2.0, 1.0, 1.0 + 1e-9])
    assert int(first(values, 60)) == 1  # within 60 eps of the minimum: the first such point
    assert int(first(values, 1)) == 3  # a tolerance of one ulp: the exact minimum
    assert int(first(jnp.asarray([2.0, jnp.nan, 1.0]), 60)) == int(
        jnp.argmin(jnp.asarray([2.0, jnp.nan, 1.0]))
    )
    assert int(first(jnp.asarray([0.0, 0.0, -0.0]), 60)) == 0
