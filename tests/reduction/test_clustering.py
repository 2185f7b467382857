"""Distribution-similarity clustering (seed 000 eqs 23–28, seed 003 eqs 4–9)."""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax.mixture import GaussianMixture, pad
from gmjax.reduction.clustering import (
    _nearness_ranks,
    centre_distances,
    combine_identical,
    gauss_cluster,
    judgment_matrix,
    resolve_overlaps,
    similarity_thresholds,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from references import pcm_numpy as ref  # noqa: E402


def scalar_gm(means, sigmas, weights=None, capacity=None, dtype=jnp.float64):
    n = len(means)
    w = np.ones(n) if weights is None else np.asarray(weights)
    return GaussianMixture.create(
        w, np.asarray(means, float), np.asarray(sigmas, float) ** 2, capacity=capacity, dtype=dtype
    )


def rows(*sets, K):
    m = np.zeros((K, K), bool)
    for i, s in enumerate(sets):
        for j in s:
            m[i, j] = True
    return jnp.asarray(m)


def as_sets(membership):
    return [set(np.flatnonzero(r).tolist()) for r in np.asarray(membership)]


def line_dist(positions):
    x = np.asarray(positions, float)
    return jnp.asarray(np.abs(x[:, None] - x[None, :]))


# --------------------------------------------------------------------------- eq 24: judgment matrix


def test_thresholds_scalar_closed_form():
    gm = scalar_gm([1.0, 1.5, 2.0, 3.0], [1.0, 1.2, 0.5, 0.8], capacity=6)
    delta = np.asarray(similarity_thresholds(gm))
    mu = np.array([1.0, 1.5, 2.0, 3.0])
    sd = np.array([1.0, 1.2, 0.5, 0.8])
    expect = np.abs(mu[:, None] - mu[None, :]) / np.minimum(sd[:, None], sd[None, :])
    np.testing.assert_allclose(delta[:4, :4], expect, rtol=1e-12, atol=1e-15)
    assert np.all(np.isinf(delta[4:, :])) and np.all(np.isinf(delta[:, 4:]))
    np.testing.assert_array_equal(delta, delta.T)


def test_judgment_matrix_properties_and_eq24_sign():
    # eq 24: r_ij = sign(min{s*lam*sigma_i - |u_ij|, s*lam*sigma_j - |u_ij|}), sign(0) -> +1
    gm = scalar_gm([0.0, 0.5, 2.0], [1.0, 0.5, 2.0])
    delta = similarity_thresholds(gm)
    for radius in [0.5, 1.0, 1.5, 4.0]:
        r = np.asarray(judgment_matrix(delta, radius, gm.mask))
        mu, sd = np.array([0.0, 0.5, 2.0]), np.array([1.0, 0.5, 2.0])
        d = np.abs(mu[:, None] - mu[None, :])
        eq24 = np.minimum(radius * sd[:, None] - d, radius * sd[None, :] - d) >= 0
        np.testing.assert_array_equal(r, eq24)
        assert np.all(np.diag(r)) and np.array_equal(r, r.T)
    # the boundary 0.5 = 1 * 0.5 counts as inside
    assert bool(judgment_matrix(delta, 1.0, gm.mask)[0, 1])
    tri = np.asarray(judgment_matrix(delta, 4.0, gm.mask, triangular=True))
    assert not tri[1, 0] and tri[0, 1]


def test_mahalanobis_reading_in_2d():
    # the confidence ellipsoid of component 0 is long in x and thin in y
    means = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]])
    covs = np.array([np.diag([4.0, 0.25]), np.diag([4.0, 4.0]), np.diag([4.0, 4.0])])
    gm = GaussianMixture.create(np.ones(3), means, covs)
    delta = np.asarray(similarity_thresholds(gm))
    assert delta[0, 1] == pytest.approx(1.0)  # 2 / sqrt(4) in both directions
    assert delta[0, 2] == pytest.approx(4.0)  # 2 / sqrt(0.25) from component 0's side


# --------------------------------------------------------------------------- eqs 25–28 on rows


def test_step1_combines_identical_clusters():
    m = rows({0, 1}, {0, 1}, {2}, {0, 1}, K=4)
    assert as_sets(combine_identical(m)) == [{0, 1}, set(), {2}, set()]


def test_situation1_disjoint_clusters_unchanged():
    m = rows({0, 1}, set(), {2, 3}, set(), K=4)
    out = resolve_overlaps(m, line_dist([0, 1, 5, 6]))
    assert as_sets(out) == [{0, 1}, set(), {2, 3}, set()]


@pytest.mark.parametrize("x_shared, owner", [(2.2, 1), (1.9, 0), (2.0, 0)])
def test_situation2_reassigns_to_nearest_renewed_cluster(x_shared, owner):
    # C0 = {0, 1, 2}, C1 = {2, 3, 4} share component 2 (eq 26, Situation 2). Renewed clusters
    # (eq 27) are {0, 1} and {3, 4}; eq 28 distances are |x2 - 1| and |3 - x2|; a tie goes to C0.
    m = rows({0, 1, 2}, {2, 3, 4}, set(), set(), set(), K=5)
    out = as_sets(resolve_overlaps(m, line_dist([0.0, 1.0, x_shared, 3.0, 4.0])))
    expect = [{0, 1}, {3, 4}]
    expect[owner] = expect[owner] | {2}
    assert out[:2] == expect and out[2:] == [set(), set(), set()]


def test_situation2_with_several_shared_components():
    # shared {2, 3}: 2 is nearer C0* = {0, 1}, 3 nearer C1* = {4, 5}
    m = rows({0, 1, 2, 3}, {2, 3, 4, 5}, K=6)
    out = as_sets(resolve_overlaps(m, line_dist([0.0, 1.0, 1.8, 3.3, 4.0, 5.0])))
    assert out[:2] == [{0, 1, 2}, {3, 4, 5}]


def test_situation3_subset_split_and_absorb():
    m = rows({0, 1, 2}, {1, 2}, set(), K=3)
    dist = line_dist([0.0, 1.0, 2.0])
    # seed 000: preserve C^j (the subset) and its complement
    assert as_sets(resolve_overlaps(m, dist)) == [{0}, {1, 2}, set()]
    # seed 003 H2 (absorb): the superset keeps everything
    assert as_sets(resolve_overlaps(m, dist, subset_rule="absorb")) == [{0, 1, 2}, set(), set()]
    # the other orientation: C0 subset of C1
    m2 = rows({1, 2}, {0, 1, 2}, set(), K=3)
    assert as_sets(resolve_overlaps(m2, dist)) == [{1, 2}, {0}, set()]
    assert as_sets(resolve_overlaps(m2, dist, subset_rule="absorb")) == [set(), {0, 1, 2}, set()]


def test_chain_by_hand_split_and_absorb():
    # A=0, B=0.6, C=1.5, sigma=1, scope 1*sigma: A~B, B~C, not A~C.
    # rows {A,B}, {A,B,C}, {B,C}. Split: (A,B) subset -> C_A={A,B}, C_B={C}; (A,C) share B,
    # d(B,A)=0.6 < d(B,C)=0.9 -> A; (B,C) identical {C} -> combined. Answer {A,B}, {C}.
    gm = scalar_gm([0.0, 0.6, 1.5], [1.0, 1.0, 1.0])
    res = gauss_cluster(gm, 1.0, range_scale=1.0)
    np.testing.assert_array_equal(res.labels, [0, 0, 1])
    assert int(res.n_clusters) == 2
    # absorb: (A,B) -> C_B takes all, C_A empty; (B,C) C_C subset -> empty. One cluster, head B.
    res = gauss_cluster(gm, 1.0, range_scale=1.0, subset_rule="absorb")
    np.testing.assert_array_equal(res.labels, [1, 1, 1])
    # seed 003 upper-triangular rows: {A,B}, {B,C}, {C}; (A,B) share B: C_A*={A}, C_B*={C},
    # d(B,A)=0.6 < 0.9 -> A; (B,C) identical {C} -> combined. Answer {A,B}, {C}.
    res = gauss_cluster(gm, 1.0, range_scale=1.0, triangular=True, subset_rule="absorb")
    np.testing.assert_array_equal(res.labels, [0, 0, 1])


def test_bridge_component_by_hand():
    # M=1.0 bridges {A=0.1, B=0.3} and {C=1.6, D=1.9} (sigma=1, scope 1*sigma).
    # rows A,B: {A,B,M}; M: all; C,D: {M,C,D}. Step 1 empties B, D. (A,M): subset -> C_A={A,B,M},
    # C_M={C,D}. (A,C) share M: d(M,{A,B})=0.7 > d(M,{C,D})=0.6 -> C_C={M,C,D}. (M,C): C_M subset
    # of C_C -> C_C={M}. Answer {A,B}, {C,D}, {M}.
    gm = scalar_gm([0.1, 0.3, 1.0, 1.6, 1.9], [1.0] * 5)
    res = gauss_cluster(gm, 1.0, range_scale=1.0)
    np.testing.assert_array_equal(res.labels, [0, 0, 3, 2, 2])


def test_paper_static_counts_with_range_scale():
    # seed 000 Table 3 (bimodal): 4, 3, 2, 2 clusters at lambda = 1..4 (reproduced exactly)
    gm = scalar_gm([0.5, 2, 3.5, 4], [1, 1.2, 0.5, 0.8], [0.3, 0.1, 0.4, 0.2])
    counts = [int(gauss_cluster(gm, lam).n_clusters) for lam in (1.0, 2.0, 3.0, 4.0)]
    assert counts == [4, 3, 2, 2]


# --------------------------------------------------------------------------- against the reference


def random_gm(rng, K, d, capacity=None, dtype=jnp.float64):
    means = rng.uniform(-3, 3, (K, d))
    A = rng.normal(size=(K, d, d)) * 0.5
    covs = A @ np.swapaxes(A, 1, 2) + np.eye(d) * rng.uniform(0.2, 1.0, (K, 1, 1))
    w = rng.uniform(0.05, 1, K)
    return GaussianMixture.create(w, means, covs, capacity=capacity, dtype=dtype), means, covs


# one capacity (K = 12) throughout, so the compiled kernels are shared between tests
@pytest.mark.parametrize("seed, d", [(0, 1), (1, 2), (3, 3)])
@pytest.mark.parametrize("triangular, rule", [(False, "split"), (True, "absorb"), (False, "absorb")])
def test_matches_numpy_reference(seed, d, triangular, rule):
    K = 12
    rng = np.random.default_rng(seed)
    gm, means, covs = random_gm(rng, K, d)
    for lam in (1.0, 2.0, 3.5, 6.0):
        res = gauss_cluster(gm, lam, triangular=triangular, subset_rule=rule)
        clusters = ref.cluster(means, covs, lam, triangular, rule)
        expect = np.full(K, -1)
        for head, members in enumerate(clusters):
            for m in members:
                expect[m] = head
        np.testing.assert_array_equal(np.asarray(res.labels), expect)
        assert int(res.n_clusters) == sum(1 for c in clusters if c)


@pytest.mark.parametrize("triangular, rule", [(False, "split"), (True, "absorb")])
def test_grid_of_lambdas_equals_one_lambda_at_a_time_and_the_reference(triangular, rule):
    """A (G,) grid is resolved in one sweep; each clustering equals the scalar call and the NumPy loop.
    K = 40 needs two 32-bit words per packed row."""
    K = 40
    gm, means, covs = random_gm(np.random.default_rng(21), K, 2)
    lams = jnp.asarray([0.5, 1.0, 2.0, 3.0, 4.5, 7.0])
    grid = gauss_cluster(gm, lams, triangular=triangular, subset_rule=rule)
    assert grid.labels.shape == (6, K) and grid.membership.shape == (6, K, K)
    for g, lam in enumerate(lams):
        one = gauss_cluster(gm, lam, triangular=triangular, subset_rule=rule)
        for a, b in zip(one, grid):
            np.testing.assert_array_equal(a, b[g])
        expect = np.full(K, -1)
        for head, members in enumerate(ref.cluster(means, covs, float(lam), triangular, rule)):
            expect[list(members)] = head
        np.testing.assert_array_equal(np.asarray(one.labels), expect)
    # a stack of membership matrices is resolved as each one alone
    stack = grid.judgment
    dist = centre_distances(gm)
    both = resolve_overlaps(stack, dist, subset_rule=rule)
    for g in range(stack.shape[0]):
        np.testing.assert_array_equal(both[g], resolve_overlaps(stack[g], dist, subset_rule=rule))
    with pytest.raises(ValueError, match="lam"):
        gauss_cluster(gm, jnp.ones((2, 2)))


@pytest.mark.parametrize("triangular, rule", [(False, "split"), (True, "absorb")])
def test_ties_of_eq28_match_the_reference(triangular, rule):
    """Centres on an integer lattice, some repeated: many equal centre distances, so eq 28's tie rule
    (to the lower-indexed cluster) decides often. The sweep compares nearest-member *ranks*
    (``_nearness_ranks``), which must decide every tie as the distances do (the NumPy loop)."""
    K = 12
    rng = np.random.default_rng(28)
    lams = (1.0, 2.0, 3.5, 6.0)
    for d in (1, 2):
        for _ in range(3):
            means = rng.integers(-2, 3, (K, d)).astype(float)
            means[K - 3 :] = means[:3]  # repeated centres
            covs = np.einsum("k,ij->kij", rng.choice([0.5, 1.0, 2.0], K), np.eye(d))
            gm = GaussianMixture.create(np.full(K, 1.0 / K), means, covs)
            grid = gauss_cluster(gm, jnp.asarray(lams), triangular=triangular, subset_rule=rule)
            for g, lam in enumerate(lams):
                expect = np.full(K, -1)
                for head, members in enumerate(ref.cluster(means, covs, lam, triangular, rule)):
                    expect[list(members)] = head
                np.testing.assert_array_equal(np.asarray(grid.labels[g]), expect)


def test_nearness_ranks_preserve_each_columns_order():
    rng = np.random.default_rng(3)
    dist = rng.integers(0, 4, (9, 9)).astype(float)  # many ties
    R2 = np.asarray(_nearness_ranks(jnp.asarray(dist)))  # twice the ranks, the low bit free
    assert R2.dtype == np.uint8 and np.all(R2 % 2 == 0)
    for m in range(9):
        for k in range(9):
            np.testing.assert_array_equal(R2[k, m] <= R2[:, m], dist[k, m] <= dist[:, m])
    assert _nearness_ranks(jnp.zeros((200, 200))).dtype == jnp.uint16


def test_partition_property():
    rng = np.random.default_rng(7)
    gm, _, _ = random_gm(rng, 10, 2, capacity=12)
    for lam in np.linspace(0.5, 8, 6):
        res = gauss_cluster(gm, lam)
        M = np.asarray(res.membership)
        live = np.asarray(gm.mask)
        np.testing.assert_array_equal(M.sum(axis=0), live.astype(int))
        lab = np.asarray(res.labels)
        assert np.all(lab[~live] == -1)
        assert len(set(lab[live].tolist())) == int(res.n_clusters)
        # a head belongs to its own cluster's row index, and only live rows are non-empty
        assert not M[~live].any()


# --------------------------------------------------------------------------- jit / vmap / padding


def test_jit_equals_eager_and_vmap_equals_loop():
    rng = np.random.default_rng(3)
    gm, _, _ = random_gm(rng, 12, 2)
    lams = jnp.linspace(0.5, 5.0, 5)
    eager = [gauss_cluster(gm, lam).labels for lam in lams]
    jitted = jax.jit(lambda g, lam: gauss_cluster(g, lam).labels)
    batched = jax.vmap(lambda lam: gauss_cluster(gm, lam).labels)(lams)
    for k, lam in enumerate(lams):
        np.testing.assert_array_equal(eager[k], jitted(gm, lam))
        np.testing.assert_array_equal(eager[k], batched[k])
    gms = [random_gm(np.random.default_rng(s), 12, 2)[0] for s in range(3)]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gms)
    out = jax.vmap(lambda g: gauss_cluster(g, 2.0).labels)(stacked)
    for k, g in enumerate(gms):
        np.testing.assert_array_equal(out[k], gauss_cluster(g, 2.0).labels)


@pytest.mark.parametrize("triangular, rule", [(False, "split"), (True, "absorb")])
def test_pooled_sweep_under_vmap_equals_each_mixture_alone(triangular, rule):
    """Under ``vmap`` the grid clusterings of all mixtures are swept from one pool by lanes that
    take the next clustering when done, and a clustering equal to its predecessor is copied
    (``clustering._sweep``): each mixture's partitions must be those it gets alone and the NumPy
    loop's. Mixtures of very different overlap (so the lanes finish at different steps), a grid
    with repeated ``λ`` (equal neighbours), two words per packed row (K = 40), nested ``vmap``, and
    a batch over ``λ`` only (ranks shared, not batched)."""
    K, B = 40, 12
    rng = np.random.default_rng(46)
    lams = jnp.asarray([0.5, 1.0, 1.0, 1.5, 2.5, 2.5, 2.5, 4.0])
    gms, refs = [], []
    for b in range(B):
        gm, means, covs = random_gm(rng, K, 1)
        spread = [0.2, 1.0, 5.0][b % 3]  # crowded to sparse: few to many pair splits
        means = means * spread
        gms.append(GaussianMixture.create(np.full(K, 1.0 / K), means, covs))
        refs.append((means, covs))
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gms)
    cluster = lambda g: gauss_cluster(g, lams, triangular=triangular, subset_rule=rule).labels  # noqa: E731
    batched = jax.jit(jax.vmap(cluster))(stacked)
    nested = jax.vmap(jax.vmap(cluster))(
        jax.tree_util.tree_map(lambda a: a.reshape((3, 4) + a.shape[1:]), stacked)
    )
    np.testing.assert_array_equal(nested.reshape(batched.shape), batched)
    for b, gm in enumerate(gms):
        np.testing.assert_array_equal(batched[b], cluster(gm))
        if b < 3:
            for g, lam in enumerate(np.asarray(lams)):
                expect = np.full(K, -1)
                for head, members in enumerate(ref.cluster(*refs[b], float(lam), triangular, rule)):
                    expect[list(members)] = head
                np.testing.assert_array_equal(np.asarray(batched[b, g]), expect)
    over_lam = jax.vmap(
        lambda lam: gauss_cluster(gms[0], lam, triangular=triangular, subset_rule=rule).labels
    )(lams)
    np.testing.assert_array_equal(over_lam, batched[0])


def test_padding_does_not_change_the_clustering():
    rng = np.random.default_rng(11)
    gm, _, _ = random_gm(rng, 9, 1)
    base = gauss_cluster(gm, 2.5)
    padded = gauss_cluster(pad(gm, 12), 2.5)
    np.testing.assert_array_equal(padded.labels[:9], base.labels)
    assert np.all(np.asarray(padded.labels[9:]) == -1)
    assert int(padded.n_clusters) == int(base.n_clusters)
    # interleaved padding: live slots keep their relative order, so heads map through the slots
    slots = np.array([0, 2, 3, 5, 6, 7, 9, 10, 11])
    K = 12
    w = np.zeros(K)
    m = np.zeros((K, 1))
    P = np.tile(np.eye(1), (K, 1, 1))
    mask = np.zeros(K, bool)
    w[slots] = np.asarray(gm.weights)
    m[slots] = np.asarray(gm.means)
    P[slots] = np.asarray(gm.covs)
    mask[slots] = True
    holes = GaussianMixture(jnp.asarray(w), jnp.asarray(m), jnp.asarray(P), jnp.asarray(mask))
    lab = np.asarray(gauss_cluster(holes, 2.5).labels)
    np.testing.assert_array_equal(lab[slots], slots[np.asarray(base.labels)])
    assert np.all(lab[~mask] == -1)


def test_float32_matches_float64():
    rng = np.random.default_rng(5)
    g64, means, covs = random_gm(rng, 12, 2)
    g32 = GaussianMixture.create(np.asarray(g64.weights), means, covs, dtype=jnp.float32)
    for lam in (1.0, 2.0, 4.0):
        # thresholds well away from lam so rounding cannot flip a comparison
        delta = np.asarray(similarity_thresholds(g64))
        assert np.min(np.abs(delta - 0.5 * lam)) > 1e-4
        r32 = gauss_cluster(g32, jnp.float32(lam))
        assert r32.labels.dtype == jnp.int32
        np.testing.assert_array_equal(r32.labels, gauss_cluster(g64, lam).labels)


def test_cluster_dims_equals_marginal():
    rng = np.random.default_rng(9)
    gm, _, _ = random_gm(rng, 12, 3)
    from gmjax.mixture import marginal

    full = gauss_cluster(gm, 2.0, dims=(0, 2))
    marg = gauss_cluster(marginal(gm, (0, 2)), 2.0)
    np.testing.assert_array_equal(full.labels, marg.labels)
    np.testing.assert_allclose(centre_distances(gm, (0, 2)), centre_distances(marginal(gm, (0, 2))))


def test_bad_subset_rule():
    with pytest.raises(ValueError, match="subset_rule"):
        resolve_overlaps(rows({0}, K=1), line_dist([0.0]), subset_rule="merge")
