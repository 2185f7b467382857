import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from gmjax import GaussianMixture
from gmjax import mixture as mx


def random_gm(seed, K=4, d=2, capacity=None, dtype=None):
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.1, 1.0, K)
    m = rng.normal(size=(K, d)) * 2
    A = rng.normal(size=(K, d, d))
    P = A @ np.swapaxes(A, 1, 2) + 0.5 * np.eye(d)
    return GaussianMixture.create(w, m, P, capacity=capacity, dtype=dtype), (w / w.sum(), m, P)


def scipy_pdf(w, m, P, x):
    return sum(wk * stats.multivariate_normal(mk, Pk).pdf(x) for wk, mk, Pk in zip(w, m, P))


# ---------------------------------------------------------------- construction and validation


def test_create_pads_with_harmless_slots():
    gm, _ = random_gm(0, K=3, d=2, capacity=5)
    assert gm.capacity == 5 and gm.dim == 2
    np.testing.assert_array_equal(gm.mask, [True, True, True, False, False])
    np.testing.assert_allclose(gm.weights[3:], 0)
    np.testing.assert_allclose(gm.means[3:], 0)
    np.testing.assert_allclose(gm.covs[3:], np.broadcast_to(np.eye(2), (2, 2, 2)))
    np.testing.assert_allclose(gm.weights.sum(), 1.0)
    mx.check(gm)


def test_create_accepts_scalar_variances_and_diagonals():
    gm = GaussianMixture.create([1, 1], [0.0, 1.0], [2.0, 3.0])
    np.testing.assert_allclose(gm.covs[:, 0, 0], [2.0, 3.0])
    gm2 = GaussianMixture.create([1], [[0.0, 1.0]], [[2.0, 3.0]])
    np.testing.assert_allclose(gm2.covs[0], np.diag([2.0, 3.0]))


def test_create_without_normalization_keeps_weights():
    gm = GaussianMixture.create([2.0, 3.0], [0.0, 1.0], [1.0, 1.0], normalize=False)
    np.testing.assert_allclose(gm.weights, [2.0, 3.0])


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(weights=[1, np.nan], means=[0.0, 1.0], covs=[1.0, 1.0]), r"weights: non-finite .* component 1"),
        (dict(weights=[1, 1], means=[0.0, np.inf], covs=[1.0, 1.0]), r"means: non-finite .* component 1"),
        (dict(weights=[1, 1], means=[0.0, 1.0], covs=[1.0, np.nan]), r"covs: non-finite .* component 1"),
        (dict(weights=[1, -0.5], means=[0.0, 1.0], covs=[1.0, 1.0]), r"weights: negative .* index 1"),
        (dict(weights=[0, 0], means=[0.0, 1.0], covs=[1.0, 1.0]), r"weights: all live weights are zero"),
        (
            dict(weights=[1, 1], means=[0.0, 1.0], covs=[1.0, -1.0]),
            r"covs: component 1 is not positive definite",
        ),
        (dict(weights=[1, 1], means=[0.0, 1.0, 2.0], covs=[1.0, 1.0]), r"means: expected shape"),
        (dict(weights=[1, 1], means=[[0.0, 0.0], [1.0, 1.0]], covs=[1.0, 1.0]), r"covs: expected shape"),
        (dict(weights=[1, 1], means=[0.0, 1.0], covs=[1.0, 1.0], capacity=1), r"capacity: 1 is smaller"),
        (dict(weights=[], means=np.zeros((0, 1)), covs=np.zeros((0, 1, 1))), r"weights: a mixture needs"),
    ],
)
def test_create_rejects_bad_input(kwargs, message):
    with pytest.raises(ValueError, match=message):
        GaussianMixture.create(**kwargs)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(weights=[1.0], means=[1e300], covs=[1.0]), r"means: component 0 overflows float32"),
        (
            dict(weights=[1.0, 1.0], means=[0.0, 1.0], covs=[1.0, 1e-50]),
            r"covs: component 1 is not positive definite in float32",
        ),
        (
            dict(weights=[1e300, 1e300], means=[0.0, 1.0], covs=[1.0, 1.0], normalize=False),
            r"weights: component 0 overflows float32",
        ),
        (
            dict(weights=[1.0, 1e-50], means=[0.0, 1.0], covs=[1.0, 1.0]),
            r"weights: weight 1e-50 at index 1 underflows to 0 in float32",
        ),
        (
            dict(weights=[1.0], means=[[0.0, 0.0]], covs=[[[1.0, 1.0 - 1e-12], [1.0 - 1e-12, 1.0]]]),
            r"covs: component 0 is not positive definite in float32",
        ),
    ],
)
def test_create_validates_after_casting(kwargs, message):
    """Values float64 holds but float32 does not are refused, naming the field (issue 15, item 3)."""
    GaussianMixture.create(**kwargs, dtype=jnp.float64)  # fine in float64
    with pytest.raises(ValueError, match=message):
        GaussianMixture.create(**kwargs, dtype=jnp.float32)


def test_create_huge_weights_and_integer_dtypes():
    # normalising [1e308, 1e308] must not overflow the sum (it gave [0, 0])
    for dtype in (jnp.float32, jnp.float64):
        gm = GaussianMixture.create([1e308, 1e308], [0.0, 1.0], [1.0, 1.0], dtype=dtype)
        np.testing.assert_array_equal(np.asarray(gm.weights), [0.5, 0.5])
    with pytest.raises(ValueError, match=r"weights: their sum overflows float64"):
        GaussianMixture.create([1e308, 1e308], [0.0, 1.0], [1.0, 1.0], normalize=False, dtype=jnp.float64)
    for dtype in ("int32", jnp.int64, bool):
        with pytest.raises(ValueError, match=r"dtype: a mixture needs a floating dtype"):
            GaussianMixture.create([1.0, 1.0], [0.0, 1.0], [1.0, 1.0], dtype=dtype)
    gm, _ = random_gm(0, K=2)
    with pytest.raises(ValueError, match=r"weights: a mixture needs a floating dtype"):
        mx.check(gm._replace(weights=jnp.asarray([1, 0], jnp.int32)))
    # integer inputs with a floating dtype are fine
    assert GaussianMixture.create([1, 1], [0, 1], [1, 2]).weights.dtype == jnp.float64


def test_create_rejects_nonsymmetric_covariance():
    P = np.array([[[1.0, 0.5], [0.0, 1.0]]])
    with pytest.raises(ValueError, match=r"covs: component 0 is not symmetric"):
        GaussianMixture.create([1.0], [[0.0, 0.0]], P)


def test_check_rejects_all_false_mask_and_dirty_padding():
    gm, _ = random_gm(1, K=2, capacity=3)
    with pytest.raises(ValueError, match="mask: no live component"):
        mx.check(gm._replace(mask=jnp.zeros(3, bool)))
    with pytest.raises(ValueError, match="mask: padded slot 2"):
        mx.check(gm._replace(means=gm.means.at[2].set(1.0)))
    with pytest.raises(ValueError, match="mask: expected a bool"):
        mx.check(gm._replace(mask=gm.mask.astype(jnp.int32)))
    with pytest.raises(ValueError, match="weights: negative"):
        mx.check(gm._replace(weights=gm.weights.at[0].set(-1.0)))


# ---------------------------------------------------------------- densities


@pytest.mark.parametrize("d", [1, 2, 3])
def test_pdf_logpdf_match_scipy(d):
    gm, (w, m, P) = random_gm(d, K=4, d=d, capacity=6)
    rng = np.random.default_rng(10 + d)
    xs = rng.normal(size=(7, d)) * 2
    expected = np.array([scipy_pdf(w, m, P, x) for x in xs])
    np.testing.assert_allclose(mx.pdf(gm, xs), expected, rtol=1e-11)
    np.testing.assert_allclose(mx.logpdf(gm, xs), np.log(expected), rtol=1e-11)
    np.testing.assert_allclose(mx.pdf(gm, xs[0]), expected[0], rtol=1e-11)
    assert mx.pdf(gm, xs[0]).shape == ()


def test_results_unchanged_by_padding():
    gm, _ = random_gm(5, K=3, d=2)
    padded = mx.pad(gm, 8)
    x = jnp.array([[0.1, -0.3], [1.0, 2.0]])
    np.testing.assert_allclose(mx.logpdf(padded, x), mx.logpdf(gm, x), rtol=1e-14)
    for f in (mx.mean, mx.cov, mx.n_active):
        np.testing.assert_allclose(f(padded), f(gm), rtol=1e-14)
    # padded slots in the middle, not only at the end: [c0, pad, pad, c1, c2] with the same weights
    head = mx.pad(jax.tree_util.tree_map(lambda a: a[:1], gm), 3)
    tail = jax.tree_util.tree_map(lambda a: a[1:], gm)
    mid = mx.concat(head, tail)
    np.testing.assert_array_equal(mid.mask, [True, False, False, True, True])
    np.testing.assert_allclose(mx.logpdf(mid, x), mx.logpdf(gm, x), rtol=1e-14)
    np.testing.assert_allclose(mx.cov(mid), mx.cov(gm), rtol=1e-14)


def test_logpdf_gradient_finite_with_padding():
    gm, _ = random_gm(6, K=3, d=2, capacity=5)

    def f(weights, means, covs):
        return mx.logpdf(GaussianMixture(weights, means, covs, gm.mask), jnp.array([0.2, 0.1]))

    grads = jax.grad(f, argnums=(0, 1, 2))(gm.weights, gm.means, gm.covs)
    for g in grads:
        assert np.all(np.isfinite(g))


# ---------------------------------------------------------------- moments and sampling


def test_moments_closed_form():
    gm, (w, m, P) = random_gm(7, K=4, d=2, capacity=6)
    mu = w @ m
    C = sum(wk * (Pk + np.outer(mk - mu, mk - mu)) for wk, mk, Pk in zip(w, m, P))
    np.testing.assert_allclose(mx.mean(gm), mu, rtol=1e-13)
    np.testing.assert_allclose(mx.cov(gm), C, rtol=1e-13)


def test_sample_moments_within_standard_error():
    gm, _ = random_gm(8, K=3, d=2, capacity=5)
    n = 200_000
    xs = np.asarray(mx.sample(gm, jax.random.key(0), n))
    mu, C = np.asarray(mx.mean(gm)), np.asarray(mx.cov(gm))
    se_mean = np.sqrt(np.diag(C) / n)
    assert np.all(np.abs(xs.mean(0) - mu) < 5 * se_mean)
    # standard error of a sample variance from the fourth central moment, estimated from the sample
    dev = xs - xs.mean(0)
    se_var = np.sqrt((np.mean(dev**4, 0) - np.var(xs, 0) ** 2) / n)
    assert np.all(np.abs(np.var(xs, 0) - np.diag(C)) < 5 * se_var)
    assert np.isfinite(xs).all()


def test_sample_never_draws_padded_slots():
    gm = GaussianMixture.create([1.0], [[100.0]], [[1e-6]], capacity=4)
    xs = mx.sample(gm, jax.random.key(1), 1000)
    assert np.all(np.abs(np.asarray(xs) - 100.0) < 0.01)


# ---------------------------------------------------------------- structural operations


def test_compact_is_stable_partition():
    gm, _ = random_gm(9, K=3, d=1, capacity=3)
    gm = mx.concat(mx.pad(mx.top_k(gm, 1), 2), gm)  # live, pad, live, live, live
    np.testing.assert_array_equal(gm.mask, [True, False, True, True, True])
    c = mx.compact(gm)
    np.testing.assert_array_equal(c.mask, [True, True, True, True, False])
    np.testing.assert_allclose(c.means[:4], gm.means[np.array([0, 2, 3, 4])])
    mx.check(c._replace(weights=c.weights))


def test_pad_rejects_shrinking():
    gm, _ = random_gm(10, K=3, capacity=3)
    with pytest.raises(ValueError, match="capacity"):
        mx.pad(gm, 2)


def test_top_k_keeps_heaviest_and_renormalizes():
    gm = GaussianMixture.create([0.1, 0.5, 0.15, 0.25], [0.0, 1.0, 2.0, 3.0], [1.0] * 4, capacity=6)
    t = mx.top_k(gm, 2)
    np.testing.assert_allclose(t.weights, [0.5, 0.25])
    np.testing.assert_allclose(t.means[:, 0], [1.0, 3.0])
    t2 = mx.top_k(gm, 2, renormalize=True)
    np.testing.assert_allclose(t2.weights.sum(), 1.0)
    big = mx.top_k(gm, 8)
    assert big.capacity == 8 and int(mx.n_active(big)) == 4
    mx.check(big)


def test_heaviest_slots_select_as_lax_top_k():
    """``heaviest_slots`` ranks float64 weights by comparisons of their total-order keys up to
    K = 64 (``lax.top_k`` above, and for float32): the same slots in the same order as
    ``lax.top_k`` over the kept weights, with ties (lower slot first), NaN, infinities and signed
    zeros, alone and under ``vmap``; ``descending_ranks`` (compared in both dtypes, sorting above
    K = 64) is the inverse of ``top_k``'s permutation."""
    rng = np.random.default_rng(46)
    specials = np.array([np.nan, -np.nan, np.inf, -np.inf, 0.0, -0.0, 1.0, 2.0])
    for trial in range(60):
        K = int([1, 2, 5, 20, 60, 64, 65, 200][trial % 8])
        for dtype in (np.float64, np.float32):
            w = rng.choice([0.1, 0.2, 0.5], K) if trial % 3 == 0 else rng.uniform(size=K)  # ties
            if trial % 2 == 0:
                w[rng.integers(0, K, max(1, K // 4))] = rng.choice(specials, max(1, K // 4))
            w = jnp.asarray(w.astype(dtype))
            keep = jnp.asarray(rng.uniform(size=K) < 0.7)
            k = int(rng.integers(1, K + 3))
            idx, valid = mx.heaviest_slots(w, keep, k)
            expected = jax.lax.top_k(jnp.where(keep, w, -jnp.inf), min(k, K))[1]
            np.testing.assert_array_equal(idx[: min(k, K)], expected)
            np.testing.assert_array_equal(valid[: min(k, K)], keep[expected])
            assert idx.shape == valid.shape == (k,) and not np.any(valid[K:])
            order = jax.lax.top_k(w, K)[1]
            np.testing.assert_array_equal(np.asarray(mx.descending_ranks(w))[np.asarray(order)], np.arange(K))
    ws = jnp.asarray(rng.choice([0.1, 0.2, 0.5, np.nan], (7, 60)))
    batched = jax.vmap(lambda w: mx.heaviest_slots(w, w > 0.15, 20)[0])(ws)
    for b in range(7):
        np.testing.assert_array_equal(batched[b], mx.heaviest_slots(ws[b], ws[b] > 0.15, 20)[0])


def test_marginal_and_affine_match_closed_form():
    gm, (w, m, P) = random_gm(11, K=3, d=3, capacity=4)
    marg = mx.marginal(gm, [0, 2])
    np.testing.assert_allclose(marg.covs[:3], P[:, [0, 2]][:, :, [0, 2]])
    A = np.array([[1.0, 2.0, 0.0], [0.0, 1.0, -1.0]])
    b = np.array([0.5, -1.0])
    aff = mx.affine(gm, A, b)
    np.testing.assert_allclose(mx.mean(aff), A @ np.asarray(mx.mean(gm)) + b, rtol=1e-12)
    np.testing.assert_allclose(mx.cov(aff), A @ np.asarray(mx.cov(gm)) @ A.T, rtol=1e-12)
    mx.check(aff)


def test_normalize_and_total_weight():
    gm = GaussianMixture.create([2.0, 6.0], [0.0, 1.0], [1.0, 1.0], capacity=3, normalize=False)
    np.testing.assert_allclose(mx.total_weight(gm), 8.0)
    np.testing.assert_allclose(mx.normalize(gm).weights, [0.25, 0.75, 0.0])


def test_from_gaussian_and_from_arrays_sanitize():
    g = mx.from_gaussian(jnp.array([1.0, 2.0]), 2 * jnp.eye(2), capacity=3)
    mx.check(g)
    dirty = GaussianMixture.from_arrays(
        jnp.array([1.0, 5.0]),
        jnp.array([[0.0], [7.0]]),
        jnp.array([[[1.0]], [[-3.0]]]),
        jnp.array([True, False]),
    )
    mx.check(dirty)


# ---------------------------------------------------------------- transformations


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_dtype_generic(dtype):
    gm, _ = random_gm(12, K=3, d=2, capacity=4, dtype=dtype)
    assert gm.means.dtype == dtype
    x = jnp.zeros((3, 2), dtype)
    assert mx.logpdf(gm, x).dtype == dtype
    assert mx.mean(gm).dtype == dtype
    assert mx.sample(gm, jax.random.key(0), 4).dtype == dtype
    gm64, _ = random_gm(12, K=3, d=2, capacity=4, dtype=jnp.float64)
    np.testing.assert_allclose(mx.logpdf(gm, x), mx.logpdf(gm64, x.astype(jnp.float64)), rtol=1e-5)


def test_jit_equals_eager_and_vmap_equals_loop():
    gms = [random_gm(20 + i, K=3, d=2, capacity=5)[0] for i in range(4)]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gms)
    x = jnp.array([0.3, -0.2])
    f = lambda g: (mx.logpdf(g, x), mx.mean(g), mx.cov(g), mx.top_k(g, 2).weights)  # noqa: E731
    batched = jax.jit(jax.vmap(f))(stacked)
    for i, g in enumerate(gms):
        eager = f(g)
        for b, e in zip(batched, eager):
            np.testing.assert_allclose(b[i], e, rtol=1e-13, atol=1e-15)
