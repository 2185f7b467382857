"""gmjax.reduction.refine: the ISE refinement improves a reduction and is differentiable in its learning rate."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from test_reduction import CAP, ise
from test_reduction_utils import seeded_mixture

from gmjax import GaussianMixture
from gmjax import reduction as R


def test_ise_refine_improves():
    gm, _ = seeded_mixture(11, n=9, d=2, capacity=CAP)
    red, _ = R.runnalls(gm, 3, capacity=3)
    out, info = R.ise_refine(red, gm, n_steps=60, learning_rate=0.02)
    assert float(info.cost) <= float(info.aux["initial_ise"])
    assert float(info.cost) < 0.9 * float(info.aux["initial_ise"])
    np.testing.assert_allclose(float(info.cost), float(ise(gm, out)), rtol=1e-10)
    np.testing.assert_allclose(float(jnp.sum(out.weights)), 1.0, atol=1e-12)
    cfg = R.Refined(R.Runnalls(num_out=3, capacity=3), n_steps=60, learning_rate=0.02)
    out2, info2 = cfg(gm)
    np.testing.assert_allclose(float(info2.cost), float(info.cost), rtol=1e-12)
    assert float(info2.cost) <= float(info2.aux["initial_ise"])


def test_ise_refine_is_differentiable_in_its_learning_rate():
    gm = GaussianMixture.create([0.3, 0.2, 0.3, 0.2], [-1.0, 0.5, 3.0, 3.2], [1.0, 0.5, 2.0, 1.0], capacity=6)
    red, _ = R.runnalls(gm, 2)

    def cost(lr):
        return R.ise_refine(red, gm, n_steps=5, learning_rate=lr)[1].cost

    c, g = jax.jit(jax.value_and_grad(cost))(1e-2)
    fd = (jax.jit(cost)(1e-2 + 1e-6) - jax.jit(cost)(1e-2 - 1e-6)) / 2e-6
    assert np.isfinite(float(g))
    np.testing.assert_allclose(float(g), float(fd), rtol=1e-5)
    np.testing.assert_allclose(float(jax.jit(jax.jacfwd(cost))(1e-2)), float(g), rtol=1e-8)
