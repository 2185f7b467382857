"""gmjax.params: partition / combine and grad / value_and_grad over the differentiable leaves of a
params pytree (issue 48 item 4: ``jax.grad`` refuses the mixtures' boolean masks)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import gmjax
from gmjax import GaussianMixture, montecarlo
from gmjax.params import is_differentiable

tree_util = jax.tree_util


@pytest.fixture(scope="module")
def problem():
    """A Runnalls-GSF of EKF components on the jump system, its params and one simulated run."""
    scenario = gmjax.scenarios.jump_system.jump_system(n_steps=6)
    gsf = gmjax.filters.build_gsf(scenario.model, "ekf", gmjax.reduction.Runnalls(num_out=4), capacity=5)
    _, zs, ts = gmjax.models.simulate(scenario, jax.random.key(1))
    return scenario, gsf, zs, ts


def _total_loglik(gsf, zs, ts):
    return lambda p: gmjax.filters.run(gsf, zs, ts, params=p)[1].loglik.sum()


def _is_mask(path) -> bool:
    return tree_util.keystr(path).endswith(".mask")


@pytest.mark.parametrize(
    ("leaf", "expected"),
    [
        (1.0, True),
        (1j, True),
        (np.float32(1.0), True),
        (np.ones(3), True),
        (jnp.ones((2, 2)), True),
        (jnp.ones(2, jnp.float32), True),
        (jnp.ones(2, jnp.complex64), True),
        (1, False),
        (True, False),
        (np.int64(1), False),
        (jnp.ones(2, bool), False),
        (jnp.ones(2, jnp.int32), False),
        (np.ones(2, bool), False),
        (jax.random.key(0), False),
        (jax.random.PRNGKey(0), False),  # a legacy uint32 key
        ("ekf", False),
        (object(), False),
    ],
)
def test_is_differentiable(leaf, expected):
    assert is_differentiable(leaf) is expected


def test_is_differentiable_on_traced_leaves():
    seen = {}

    def f(x, mask, n):
        seen.update(x=is_differentiable(x), mask=is_differentiable(mask), n=is_differentiable(n))
        return x

    jax.jit(f)(jnp.ones(2), jnp.ones(2, bool), jnp.arange(2))
    assert seen == {"x": True, "mask": False, "n": False}


def test_partition_of_a_mixture_separates_the_mask():
    gm = GaussianMixture.create(weights=[0.3, 0.7], means=[[0.0], [2.0]], covs=[1.0, 0.5], capacity=4)
    diff, static = gmjax.partition(gm)
    assert isinstance(diff, GaussianMixture) and isinstance(static, GaussianMixture)
    assert diff.mask is None and static.weights is None and static.means is None and static.covs is None
    assert diff.weights is gm.weights and diff.means is gm.means and diff.covs is gm.covs
    assert static.mask is gm.mask
    assert gmjax.combine(diff, static) == gm  # NamedTuple equality: the very same leaves


def test_partition_combine_round_trip_on_a_filters_params(problem):
    _, gsf, _, _ = problem
    params = gsf.params
    diff, static = gmjax.partition(params)
    is_none = lambda x: x is None  # noqa: E731
    structure = tree_util.tree_structure(params)
    structure_none = tree_util.tree_structure(params, is_leaf=is_none)  # an original None stays None
    assert tree_util.tree_structure(diff, is_leaf=is_none) == structure_none
    assert tree_util.tree_structure(static, is_leaf=is_none) == structure_none
    # every leaf is in exactly one half; the masks (bool) and nothing differentiable are static
    pairs = zip(
        tree_util.tree_leaves_with_path(params),
        tree_util.tree_leaves(diff, is_leaf=is_none),
        tree_util.tree_leaves(static, is_leaf=is_none),
    )
    n_masks = 0
    for (path, leaf), d, s in pairs:
        assert (d is None) != (s is None), tree_util.keystr(path)
        assert (d if d is not None else s) is leaf
        if _is_mask(path):
            n_masks += 1
            assert d is None and s.dtype == bool
    assert n_masks == 3  # the prior, the process noise and the measurement noise
    for leaf in tree_util.tree_leaves(diff):
        assert is_differentiable(leaf)
        assert not isinstance(leaf, (bool, int)) and not jnp.issubdtype(jnp.result_type(leaf), jnp.integer)
        assert jnp.result_type(leaf) != jnp.bool_
    assert tree_util.tree_leaves(static) and not any(map(is_differentiable, tree_util.tree_leaves(static)))
    back = gmjax.combine(diff, static)
    assert tree_util.tree_structure(back) == structure
    assert all(a is b for a, b in zip(tree_util.tree_leaves(back), tree_util.tree_leaves(params)))
    # a predicate of one's own: only the reducer's threshold
    only, rest = gmjax.partition(params, predicate=lambda x: isinstance(x, float))
    assert tree_util.tree_leaves(only) == [params.reducer.threshold]
    assert gmjax.combine(only, rest) == params


def test_combine_keeps_none_subtrees_and_takes_the_first_leaf():
    assert gmjax.combine([None, 1, None], [0, None, None]) == [0, 1, None]
    assert gmjax.combine({"a": None, "b": 2.0}, {"a": 1, "b": None}) == {"a": 1, "b": 2.0}
    with pytest.raises(TypeError, match="at least one"):
        gmjax.combine()


def test_a_none_in_the_tree_stays_none():
    """``None`` is an empty subtree (PCM's ``lam`` by default): in both halves and in the gradient."""
    tree = {"lam": None, "x": jnp.arange(3.0), "mask": jnp.ones(3, bool), "n": 3}
    diff, static = gmjax.partition(tree)
    assert diff == {"lam": None, "x": tree["x"], "mask": None, "n": None}
    assert static == {"lam": None, "x": None, "mask": tree["mask"], "n": 3}
    assert gmjax.combine(diff, static) == tree
    grads = gmjax.grad(lambda t: jnp.sum(jnp.where(t["mask"], t["x"] ** 2, 0.0)) * t["n"])(tree)
    assert grads["lam"] is None and grads["mask"] is None and grads["n"] is None
    np.testing.assert_allclose(grads["x"], 6.0 * tree["x"])


def test_plain_jax_grad_refuses_the_masks(problem):
    """The failure this module fixes (issue 48 item 4)."""
    _, gsf, zs, ts = problem
    with pytest.raises(TypeError, match="bool"):
        jax.grad(_total_loglik(gsf, zs, ts))(gsf.params)


def test_grad_of_the_total_loglik_equals_a_central_difference(problem):
    """d loglik / d params along a random direction in all the differentiable leaves (float64)."""
    _, gsf, zs, ts = problem
    params = gsf.params
    loglik = _total_loglik(gsf, zs, ts)
    grads = jax.jit(gmjax.grad(loglik))(params)

    is_none = lambda x: x is None  # noqa: E731
    assert tree_util.tree_structure(grads, is_leaf=is_none) == tree_util.tree_structure(
        params, is_leaf=is_none
    )
    for (path, leaf), g in zip(
        tree_util.tree_leaves_with_path(params), tree_util.tree_leaves(grads, is_leaf=is_none)
    ):
        if _is_mask(path):
            assert g is None, tree_util.keystr(path)
        else:
            assert g is not None and jnp.shape(g) == jnp.shape(leaf), tree_util.keystr(path)
            assert jnp.result_type(g) == jnp.float64 and bool(jnp.all(jnp.isfinite(g)))
    cov_grad = grads.model.process_noise.covs
    assert float(jnp.abs(cov_grad).max()) > 1e-3  # the likelihood does depend on the noises

    diff, static = gmjax.partition(params)
    leaves, treedef = tree_util.tree_flatten(diff)
    keys = jax.random.split(jax.random.key(7), len(leaves))
    direction = [jax.random.normal(k, jnp.shape(x), jnp.float64) for k, x in zip(keys, leaves)]
    norm = jnp.sqrt(sum(jnp.sum(v**2) for v in direction))
    direction = treedef.unflatten([v / norm for v in direction])

    def moved(h):  # params + h * direction; the threshold is inf and stays inf
        return gmjax.combine(tree_util.tree_map(lambda x, v: x + h * v, diff, direction), static)

    f = jax.jit(loglik)
    h = 1e-5
    fd = (f(moved(h)) - f(moved(-h))) / (2 * h)
    analytic = sum(
        jnp.vdot(g, v) for g, v in zip(tree_util.tree_leaves(grads), tree_util.tree_leaves(direction))
    )
    print("directional derivative", float(analytic), "central difference", float(fd))
    assert float(analytic) == pytest.approx(float(fd), rel=1e-5)


def test_grad_passes_other_arguments_and_aux_through():
    gm = GaussianMixture.create(weights=[0.3, 0.7], means=[[0.0], [2.0]], covs=[1.0, 0.5], capacity=4)
    x = jnp.array([[0.5], [1.0]])

    def loss(g, points, *, scale):
        lp = gmjax.mixture.logpdf(g, points)
        return scale * lp.sum(), lp

    grads, aux = gmjax.grad(loss, has_aux=True)(gm, x, scale=2.0)
    (value, aux_2), grads_2 = gmjax.value_and_grad(loss, has_aux=True)(gm, x, scale=2.0)
    np.testing.assert_array_equal(aux, aux_2)
    assert float(value) == pytest.approx(2.0 * float(aux.sum()))
    assert grads.mask is None and grads_2.mask is None
    ref = jax.grad(lambda w, m, c: loss(gm._replace(weights=w, means=m, covs=c), x, scale=2.0)[0], (0, 1, 2))
    for a, b in zip((grads.weights, grads.means, grads.covs), ref(gm.weights, gm.means, gm.covs)):
        np.testing.assert_allclose(a, b, rtol=1e-12)
    np.testing.assert_allclose(grads.weights[2:], 0.0)  # padded slots do not enter the density
    with pytest.raises(TypeError, match="first argument"):
        gmjax.grad(loss)(points=x, scale=1.0)


def test_grad_of_a_study_loss_and_an_optax_step():
    """The call of issue 48 item 4 on a study, and one optax step on the differentiable half."""
    scenario = gmjax.scenarios.jump_system.jump_system(n_steps=6)
    gsf = gmjax.filters.build_gsf(scenario.model, "ekf", gmjax.reduction.PruneTop(num_out=4), capacity=5)
    key = jax.random.key(0)
    grad_fn = jax.jit(gmjax.grad(lambda p: montecarlo.study_loss(gsf, scenario, 16, key, params=p)))
    grads = grad_fn(gsf.params)
    assert grads.model.prior.mask is None and grads.model.process_noise.mask is None
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in tree_util.tree_leaves(grads))
    assert float(jnp.abs(grads.model.measurement_noise.covs).max()) > 0.0

    diff, static = gmjax.partition(gsf.params)
    opt = optax.sgd(1e-3)
    updates, _ = opt.update(grads, opt.init(diff), diff)
    new = gmjax.combine(optax.apply_updates(diff, updates), static)
    assert tree_util.tree_structure(new) == tree_util.tree_structure(gsf.params)
    assert new.model.prior.mask is gsf.params.model.prior.mask
    np.testing.assert_allclose(
        new.model.measurement_noise.covs,
        gsf.params.model.measurement_noise.covs - 1e-3 * grads.model.measurement_noise.covs,
    )
