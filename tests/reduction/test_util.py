"""The reducers' private batch bookkeeping (``gmjax.reduction._util``)."""

import jax
import jax.numpy as jnp
import numpy as np

from gmjax.reduction._util import first_where, live_first


def test_first_where_is_the_stable_argsort_of_the_runs_that_need_it():
    """The batch rules' order of the runs to gather (a running count and a scatter): the indices
    where ``need`` holds in increasing order, then ``B`` to fill ``size``, what a stable argsort of
    ``~need`` gives before its tail; alone and under jit, none, some and all needing."""
    rng = np.random.default_rng(4)
    for B, size, p in [(1000, 1024, 0.01), (1000, 1024, 0.5), (37, 64, 0.0), (37, 64, 1.0), (5, 5, 0.4)]:
        need = rng.uniform(size=B) < p
        expected = np.full(size, B)
        n = int(need.sum())
        expected[:n] = np.argsort(~need, kind="stable")[:n]
        for fn in (first_where, jax.jit(first_where, static_argnums=1)):
            got = np.asarray(fn(jnp.asarray(need), size))
            assert got.dtype == np.int32
            np.testing.assert_array_equal(got, expected)


def test_live_first_is_the_stable_argsort_of_the_dead_slots():
    """The reducers' compaction order (a running count and a scatter) against ``argsort(~mask,
    stable=True)``, and its position output the inverse permutation; alone and under ``vmap``."""
    rng = np.random.default_rng(5)
    masks = [rng.uniform(size=K) < p for K, p in [(60, 0.3), (20, 1.0), (20, 0.0), (1, 0.5), (129, 0.6)]]
    for mask in masks:
        order, position = live_first(jnp.asarray(mask))
        np.testing.assert_array_equal(order, np.argsort(~mask, kind="stable"))
        np.testing.assert_array_equal(np.asarray(position)[np.asarray(order)], np.arange(mask.size))
        assert order.dtype == position.dtype == np.int32
    stack = jnp.asarray(rng.uniform(size=(9, 30)) < 0.5)
    batched = jax.vmap(lambda m: live_first(m)[0])(stack)
    np.testing.assert_array_equal(batched, np.argsort(~np.asarray(stack), axis=1, kind="stable"))
