"""gmjax.reduction.step6: the AGSF's step-6 merge (seed 001) follows the reducer protocol, its history gates
the rules, and an overflow keeps the heaviest."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import mixture as gmm
from gmjax.mixture import GaussianMixture
from gmjax.reduction.step6 import Step6Merge, Step6State


def _three_components():
    """Two close components (slots 0, 2) and a far one (slot 3); slot 1 is padding."""
    return GaussianMixture(
        jnp.array([0.5, 0.0, 0.3, 0.2]),
        jnp.array([[0.0, 0.0], [0.0, 0.0], [0.05, 0.0], [6.0, 1.0]]),
        jnp.stack([jnp.eye(2), jnp.eye(2), 1.1 * jnp.eye(2), jnp.eye(2)]),
        jnp.array([True, False, True, True]),
    )


def test_step6_follows_the_reducer_protocol():
    gm = _three_components()
    red = Step6Merge(capacity=3)
    state = red.init(4)
    assert isinstance(state, Step6State)
    assert all(jnp.shape(leaf)[0] == 4 for leaf in jax.tree_util.tree_leaves(state))
    out, new_state, info = red.reduce(gm, state)
    out2, info2 = red(gm)  # __call__ == reduce from a fresh state
    for a, b in zip(jax.tree_util.tree_leaves((out, info)), jax.tree_util.tree_leaves((out2, info2))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # a stateful reducer returns exactly its capacity, with a state aligned with the output slots
    assert out.capacity == 3
    assert all(jnp.shape(leaf)[0] == 3 for leaf in jax.tree_util.tree_leaves(new_state))
    # rule 2 (fresh state: "close before" counts as met) merges the close pair into slot 0
    np.testing.assert_array_equal(np.asarray(info.labels), [0, -1, 0, 1])
    assert int(info.n_in) == 3 and int(info.n_out) == 2 and int(info.aux["n_merged"]) == 1
    np.testing.assert_allclose(float(jnp.sum(out.weights)), 1.0, rtol=1e-14)
    m_in, P_in = gmm.moments(gm)
    m_out, P_out = gmm.moments(out)  # moment-preserving merge (eq 39, normalised)
    np.testing.assert_allclose(np.asarray(m_out), np.asarray(m_in), rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(np.asarray(P_out), np.asarray(P_in), rtol=1e-13, atol=1e-14)
    # the new state names the output as the previous posterior
    np.testing.assert_array_equal(np.asarray(new_state.ancestor), [0, 1, 2])
    np.testing.assert_array_equal(np.asarray(new_state.ancestor_weight), np.asarray(out.weights))
    assert jax.jit(lambda g, s: red.reduce(g, s)[0].weights)(gm, state).shape == (3,)


def test_step6_history_gates_the_rules():
    gm = _three_components()
    red = Step6Merge()
    fresh = red.init(4)
    # rule 2 needs the ancestors to have been close too: distinct ancestors that were far apart
    far = fresh._replace(ancestor_cost=jnp.full((4, 4), 10.0))
    out, _, info = red.reduce(gm, far)
    assert int(info.n_out) == 3 and int(info.aux["n_merged"]) == 0
    # ... but two descendants of one ancestor were one Gaussian (cost 0 before)
    siblings = far._replace(ancestor=jnp.array([0, 1, 0, 3], jnp.int32))
    _, _, info = red.reduce(gm, siblings)
    np.testing.assert_array_equal(np.asarray(info.labels), [0, -1, 0, 1])
    # rule 3: low DON now and before merges even far components; unknown DON (inf) does not
    linear = far._replace(don=jnp.zeros(4))
    _, _, info = red.reduce(gm, linear)
    assert int(info.n_out) == 1 and int(info.aux["n_merged"]) == 2
    # rule 1: both low now and low before; pruning drops what is below prune_threshold
    light = GaussianMixture(
        jnp.array([0.99, 0.004, 0.00599, 5e-5]),
        jnp.array([[0.0], [5.0], [-5.0], [9.0]]),
        jnp.ones((4, 1, 1)),
        jnp.ones(4, bool),
    )
    st = Step6Merge().init(4)._replace(ancestor_cost=jnp.full((4, 4), 10.0))
    out, _, info = Step6Merge().reduce(light, st)
    np.testing.assert_array_equal(np.asarray(info.labels), [0, 1, 1, -1])
    np.testing.assert_allclose(float(info.pruned_mass), 5e-5, rtol=1e-12)
    st = st._replace(ancestor_weight=jnp.array([1.0, 1.0, 0.0, 0.0]))  # slot 1 was not low before
    _, _, info = Step6Merge().reduce(light, st)
    np.testing.assert_array_equal(np.asarray(info.labels), [0, 1, 2, -1])


def test_step6_overflow_keeps_the_heaviest():
    gm = _three_components()
    far = Step6Merge().init(4)._replace(ancestor_cost=jnp.full((4, 4), 10.0))
    out, _, info = Step6Merge(capacity=2).reduce(gm, far)
    assert bool(info.overflow) and int(info.n_out) == 2
    np.testing.assert_array_equal(np.asarray(info.labels), [0, -1, 1, -1])
    np.testing.assert_allclose(np.asarray(out.weights), [0.5 / 0.8, 0.3 / 0.8], rtol=1e-14)
    with pytest.raises(ValueError, match="state.don"):
        Step6Merge().reduce(gm, Step6Merge().init(3))
