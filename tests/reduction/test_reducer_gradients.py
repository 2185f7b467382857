"""Gradients through every reducer, and NaN thresholds (issue 15, items 1 and 6).

``jax.grad`` and ``jax.jacfwd`` of a downstream scalar of every reducer's output are checked against
central finite differences along random directions that move the weights, means and covariances of
the live components *and* the reducer's dynamic thresholds together, on a random mixture whose padded
slots sit between live ones. The scalar (log-density at fixed points plus ``Σ w log det P``) is not
preserved by moment-preserving merges, so the check sees the merge Jacobians, not an invariant.

Hard thresholds make piecewise-constant decisions: at a generic point the output does not move with
them (gradient exactly 0, and the finite difference agrees); the relaxed modes (``mode="soft"``) are
differentiable in their thresholds and are checked the same way. One compiled function per reducer
computes the value, both derivatives and the perturbed values, so each case compiles once.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_contract import REDUCERS

from gmjax import GaussianMixture, reduction
from gmjax import mixture as mx

K, D, PAD = 6, 2, 3
X_EVAL = jnp.asarray([[0.0, 0.0], [1.0, -1.0], [-2.0, 0.5]])
N_DIR = 3
H = 1e-6


def padded_mixture(seed: int) -> GaussianMixture:
    """``K`` live components in ``K + PAD`` slots, padded slots interleaved (not only at the end)."""
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.2, 1.0, K)
    m = rng.normal(0.0, 2.0, (K, D))
    A = rng.normal(size=(K, D, D))
    P = 0.2 * np.eye(D) + 0.3 * A @ np.swapaxes(A, -1, -2)
    gm = GaussianMixture.create(w, m, P, capacity=K + PAD)
    perm = np.asarray([0, 6, 1, 2, 7, 3, 4, 8, 5])  # slots 1, 4 and 7 padded
    return mx.check(jax.tree_util.tree_map(lambda a: a[perm], gm))


def score(out: GaussianMixture) -> jax.Array:
    """A downstream scalar that moment-preserving merges do not keep fixed."""
    logdet = jnp.linalg.slogdet(out.covs)[1]
    return jnp.sum(mx.logpdf(out, X_EVAL)) + jnp.sum(jnp.where(out.mask, out.weights * logdet, 0.0))


def _float_config(cfg):
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), cfg)


def _directions(gm: GaussianMixture, cfg, seed: int):
    """Random directions in (weights, means, covs, thresholds); zero on padded slots and on infinite
    thresholds; symmetric in the covariances; weights moved within the simplex (sum 0)."""
    rng = np.random.default_rng(seed)
    live = np.asarray(gm.mask)
    out = []
    for _ in range(N_DIR):
        dw = rng.normal(size=gm.weights.shape) * live
        dw -= live * dw.sum() / live.sum()
        dm = rng.normal(size=gm.means.shape) * live[:, None]
        B = rng.normal(size=gm.covs.shape)
        dP = 0.5 * (B + np.swapaxes(B, -1, -2)) * live[:, None, None] * 0.1
        dc = jax.tree_util.tree_map(
            lambda x: jnp.asarray(
                rng.normal() * np.isfinite(x) * 0.1 * max(1.0, abs(float(x))) if np.isfinite(x) else 0.0
            ),
            cfg,
        )
        out.append((jnp.asarray(dw), jnp.asarray(dm), jnp.asarray(dP), dc))
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *out)


def _checker(key):
    def f(params):
        w, m, P, cfg = params
        gm = GaussianMixture(w, m, P, MASK)
        return score(cfg(gm, key=key)[0])

    @jax.jit
    def check(params, dirs):
        value, grad = jax.value_and_grad(f)(params)
        fwd = jax.jacfwd(f)(params)
        move = lambda s: jax.vmap(lambda d: f(jax.tree_util.tree_map(lambda p, q: p + s * q, params, d)))(  # noqa: E731
            dirs
        )
        return value, grad, fwd, move(H), move(-H)

    return check


GM0 = padded_mixture(0)
MASK = GM0.mask

RELAXED = {
    "prune_threshold_soft": lambda: reduction.PruneThreshold(threshold=0.12, temperature=0.03, mode="soft"),
    "prune_censored_soft": lambda: reduction.PruneCensored(rho=0.8, temperature=0.05, mode="soft"),
    "pcm_soft": lambda: reduction.PCM(
        rho=0.9, lam=2.0, temperature=0.3, gate_temperature=0.05, newton_steps=0, mode="soft"
    ),
}
CASES = {**{n: f for n, f in REDUCERS.items()}, **RELAXED}
# (COWA: 18 s; its gradient also runs by default in tests/test_contract.py)
_SLOW = {"pcm", "gmrcm", "brute_force", "williams", "refined", "pcm_soft", "cowa"}


@pytest.mark.parametrize(
    "name", [n if n not in _SLOW else pytest.param(n, marks=pytest.mark.slow) for n in sorted(CASES)]
)
def test_grad_and_jacfwd_match_finite_differences_with_padding(name):
    cfg = _float_config(CASES[name]())
    params = (GM0.weights, GM0.means, GM0.covs, cfg)
    dirs = _directions(GM0, cfg, 1)
    value, grad, fwd, up, down = _checker(jax.random.key(2))(params, dirs)
    assert np.isfinite(float(value))
    for tree in (grad, fwd):
        for leaf in jax.tree_util.tree_leaves(tree):
            assert np.all(np.isfinite(np.asarray(leaf))), name
    # reverse and forward mode agree
    for a, b in zip(jax.tree_util.tree_leaves(grad), jax.tree_util.tree_leaves(fwd)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-8, atol=1e-10)
    # directional derivatives against central differences
    fd = (np.asarray(up) - np.asarray(down)) / (2 * H)
    ad = sum(
        np.asarray(d).reshape(N_DIR, -1) @ np.asarray(g).reshape(-1)
        for d, g in zip(jax.tree_util.tree_leaves(dirs), jax.tree_util.tree_leaves(grad))
    )
    np.testing.assert_allclose(ad, fd, rtol=1e-5, atol=1e-6 * max(1.0, abs(float(value))))
    # padded slots get no gradient
    pad = ~np.asarray(MASK)
    assert np.all(np.asarray(grad[1])[pad] == 0) and np.all(np.asarray(grad[2])[pad] == 0)
    # a hard threshold decides piecewise constantly: its gradient is exactly 0
    if name in REDUCERS and name not in {"refined"}:
        for leaf in jax.tree_util.tree_leaves(grad[3]):
            assert np.all(np.asarray(leaf) == 0), name


# ---------------------------------------------------------------------------------------------
# Item 6: a traced NaN threshold is a flag and a defined result (the input unchanged), never an
# empty mixture.

NAN_CASES = {
    "runnalls": lambda t: reduction.Runnalls(num_out=2, threshold=t),
    "salmond": lambda t: reduction.Salmond(num_out=2, threshold=t),
    "west": lambda t: reduction.West(num_out=2, threshold=t),
    "cowa": lambda t: reduction.COWA(num_out=2, threshold=t),
    "williams": lambda t: reduction.Williams(num_out=2, threshold=t),
    "vo_ma": lambda t: reduction.VoMa(merge_threshold=t),
    "prune_threshold": lambda t: reduction.PruneThreshold(threshold=t),
    "prune_censored": lambda t: reduction.PruneCensored(rho=t),
    "pcm_lam": lambda t: reduction.PCM(lam=t, newton_steps=0),
    "pcm_rho": lambda t: reduction.PCM(rho=t, newton_steps=0),
    "gmrcm_lam": lambda t: reduction.GMRCM(lam=t, newton_steps=0),
    "refined_lr": lambda t: reduction.Refined(reduction.Runnalls(num_out=2), n_steps=3, learning_rate=t),
}
_NAN_SLOW = {"williams", "gmrcm_lam", "refined_lr"}


@pytest.mark.parametrize(
    "name", [n if n not in _NAN_SLOW else pytest.param(n, marks=pytest.mark.slow) for n in sorted(NAN_CASES)]
)
def test_traced_nan_threshold_is_flagged_and_returns_the_input(name):
    gm = GaussianMixture.create([0.3, 0.2, 0.3, 0.2], [-1.0, 0.5, 3.0, 3.2], [1.0, 0.5, 2.0, 1.0], capacity=6)
    fine = {"pcm_rho": 0.9, "prune_censored": 0.9, "refined_lr": 1e-2, "prune_threshold": 0.25}.get(name, 0.5)
    run = jax.jit(lambda cfg, g: cfg.reduce(g, cfg.init(g.capacity), key=None))
    out, _, info = run(NAN_CASES[name](jnp.asarray(jnp.nan)), gm)
    assert bool(info.invalid_threshold)
    mx.check(out)  # never empty, never NaN
    if name == "refined_lr":  # the refinement is skipped: the base reduction, unrefined
        want, base_info = reduction.Runnalls(num_out=2)(gm)
        labels = base_info.labels
    else:
        want, labels = gm, np.where(np.asarray(gm.mask), np.arange(6), -1)
        assert float(info.cost) == 0.0
    assert int(info.n_out) == int(mx.n_active(want))
    for a, b in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(want)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(info.labels), np.asarray(labels))
    # the same compiled function with a valid threshold is not flagged
    _, _, ok = run(NAN_CASES[name](jnp.asarray(fine)), gm)
    assert not bool(ok.invalid_threshold)

    # gradients w.r.t. the mixture stay finite under the NaN threshold
    def second_moment(m):
        out = NAN_CASES[name](jnp.asarray(jnp.nan))(gm._replace(means=m))[0]
        return jnp.sum(out.weights[:, None] * out.means**2)

    g = jax.jit(jax.grad(second_moment))(gm.means)
    assert np.all(np.isfinite(np.asarray(g)))
