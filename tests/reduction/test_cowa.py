"""gmjax.reduction.cowa: the constrained weight QP against the NumPy active set and SciPy SLSQP, and
finite gradients with identical components."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import GaussianMixture, reduction
from references import reduction_np as ref


def test_cowa_weights_match_numpy():
    """COWA's constrained QP (jitted active set) equals the NumPy active set and SciPy SLSQP."""
    from scipy.optimize import minimize

    from gmjax.reduction.cowa import optimal_weights

    rng = np.random.default_rng(4)
    for _trial in range(10):
        n = 6
        X = rng.normal(size=(n, n + 2))
        S = X @ X.T + 0.1 * np.eye(n)
        b = rng.normal(size=n)
        w_ref, act_ref = ref.cowa_weights(S, b, 1.0)
        w, act = optimal_weights(S, b, np.ones(n, bool), 1.0, n)
        np.testing.assert_allclose(np.asarray(w), w_ref, atol=1e-10)
        res = minimize(
            lambda x: x @ S @ x - 2 * b @ x,
            np.full(n, 1 / n),
            method="SLSQP",
            bounds=[(0, None)] * n,
            constraints=[{"type": "eq", "fun": lambda x: x.sum() - 1}],
            options={"ftol": 1e-14, "maxiter": 500},
        )
        # the active-set answer is feasible and at least as good as SLSQP's when no weight is cut
        f = lambda x: x @ S @ x - 2 * b @ x  # noqa: E731
        if act_ref.all():
            assert f(np.asarray(w)) <= res.fun + 1e-9


def test_cowa_gradient_with_identical_components_is_finite():
    """Two pairs of identical components: COWA's weight QP is singular (NaN gradients before)."""
    gm = GaussianMixture.create(
        [0.25, 0.25, 0.25, 0.25], [0.0, 0.0, 3.0, 3.0], [1.0, 1.0, 2.0, 2.0], capacity=6
    )

    def first_moment(means):
        out = reduction.cowa(gm._replace(means=means), 2)[0]
        return jnp.sum(out.weights[:, None] * out.means)

    g = np.asarray(jax.jit(jax.grad(first_moment))(gm.means))
    gf = np.asarray(jax.jit(jax.jacfwd(first_moment))(gm.means))
    # the merges preserve the first moment, so d/dm_k sum_j w_j m_j = w_k (0 on padding)
    np.testing.assert_allclose(g[:, 0], np.asarray(gm.weights), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(gf, g, rtol=1e-12, atol=1e-15)
