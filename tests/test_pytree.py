import dataclasses

import jax
import jax.numpy as jnp
import pytest

from gmjax._pytree import pytree_dataclass, static_field


@pytree_dataclass
class Config:
    threshold: jax.Array
    n_iter: int = static_field(default=3)


def test_dynamic_fields_are_leaves_static_fields_are_not():
    cfg = Config(jnp.asarray(0.5), n_iter=4)
    leaves, treedef = jax.tree_util.tree_flatten(cfg)
    assert len(leaves) == 1
    rebuilt = jax.tree_util.tree_unflatten(treedef, leaves)
    assert rebuilt.n_iter == 4 and float(rebuilt.threshold) == 0.5
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.threshold = 1.0  # frozen


def test_changing_threshold_does_not_retrace_but_static_does():
    traces = []

    @jax.jit
    def f(cfg, x):
        traces.append(1)
        return x * cfg.threshold * cfg.n_iter

    f(Config(jnp.asarray(0.5)), 1.0)
    f(Config(jnp.asarray(0.7)), 1.0)
    assert len(traces) == 1
    f(Config(jnp.asarray(0.7), n_iter=5), 1.0)
    assert len(traces) == 2


def test_grad_reaches_dynamic_field():
    g = jax.grad(lambda c: c.threshold**2 * c.n_iter)(Config(jnp.asarray(2.0)))
    assert float(g.threshold) == pytest.approx(12.0)
