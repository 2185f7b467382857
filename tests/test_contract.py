"""The one contract: every reducer and every filter through the same generic driver.

Each reducer is driven only through ``init(capacity)`` / ``reduce(gm, state, *, key)``, and each
filter only through ``Filter(init, predict, update, params)`` and :func:`gmjax.filters.run`, under
``jit``, ``vmap`` and ``grad``; nothing here knows which algorithm it drives.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax import GaussianMixture, reduction
from gmjax import mixture as gmm

K = 6


def _mixture(seed: int, capacity: int = K + 2) -> GaussianMixture:
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.2, 1.0, K)
    means = rng.normal(0.0, 2.0, (K, 2))
    A = rng.normal(size=(K, 2, 2))
    covs = 0.2 * np.eye(2) + 0.3 * A @ np.swapaxes(A, -1, -2)
    return GaussianMixture.create(w / w.sum(), means, covs, capacity=capacity)


REDUCERS = {
    "prune_threshold": lambda: reduction.PruneThreshold(threshold=0.1),
    "prune_top": lambda: reduction.PruneTop(num_out=3),
    "prune_censored": lambda: reduction.PruneCensored(rho=0.9),
    "runnalls": lambda: reduction.Runnalls(num_out=3),
    "west": lambda: reduction.West(num_out=3),
    "salmond": lambda: reduction.Salmond(num_out=3),
    "williams": lambda: reduction.Williams(num_out=3),
    "cowa": lambda: reduction.COWA(num_out=3),
    "gmrc": lambda: reduction.GMRC(num_out=3),
    "kmeans": lambda: reduction.KMeans(num_out=3),
    "vo_ma": lambda: reduction.VoMa(merge_threshold=1.0),
    "brute_force": lambda: reduction.BruteForce(num_out=3),
    "refined": lambda: reduction.Refined(reduction.Runnalls(num_out=3), n_steps=5),
    "pcm": lambda: reduction.PCM(newton_steps=2),
    "gmrcm": lambda: reduction.GMRCM(newton_steps=2),
}


def drive(reducer, gm: GaussianMixture, key):
    """The generic driver: a fresh state, one reduction (what every filter does)."""
    state = reducer.init(gm.capacity)
    return reducer.reduce(gm, state, key=key)


@pytest.mark.parametrize("name", sorted(REDUCERS))
def test_every_reducer_follows_the_protocol_under_jit_and_vmap(name):
    reducer = REDUCERS[name]()
    gm = _mixture(0)
    key = jax.random.key(1)
    out, state, info = drive(reducer, gm, key)
    assert isinstance(out, GaussianMixture) and isinstance(info, reduction.ReductionInfo)
    assert out.dim == gm.dim
    assert int(info.n_in) == K and 1 <= int(info.n_out) <= K
    assert info.labels.shape == (gm.capacity,)
    np.testing.assert_allclose(float(gmm.total_weight(out)), 1.0, rtol=1e-12)
    for leaf in jax.tree_util.tree_leaves(state):  # stateful: aligned with the output slots
        assert leaf.shape[0] == out.capacity
    # the config is a pytree: pass it through jit as an argument (thresholds traced)
    jitted = jax.jit(drive)(reducer, gm, key)
    for a, b in zip(jax.tree_util.tree_leaves((out, info)), jax.tree_util.tree_leaves(jitted[::2])):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-12)
    # vmap over mixtures == loop
    gms = jax.tree_util.tree_map(lambda *a: jnp.stack(a), _mixture(2), _mixture(3))
    batched = jax.jit(jax.vmap(lambda g: drive(reducer, g, key)[0]))(gms)
    for i, seed in enumerate((2, 3)):
        one = drive(reducer, _mixture(seed), key)[0]
        np.testing.assert_allclose(np.asarray(batched.means[i]), np.asarray(one.means), rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(
            np.asarray(batched.weights[i]), np.asarray(one.weights), rtol=1e-9, atol=1e-12
        )


# reducers whose output is a smooth function of the input means away from decision boundaries
# "refined" (an Adam loop over the ISE) is left out: its gradient is not checked yet
_GRAD = sorted(set(REDUCERS) - {"refined"})
_SLOW_GRAD = {"pcm", "gmrcm", "brute_force", "williams"}


@pytest.mark.parametrize(
    "name", [n if n not in _SLOW_GRAD else pytest.param(n, marks=pytest.mark.slow) for n in _GRAD]
)
def test_every_reducer_is_differentiable_in_the_mixture(name):
    """``jax.grad`` through ``reduce`` w.r.t. the component means is finite and equals a central
    finite difference (the decisions do not change within ``eps`` at this generic point)."""
    reducer = REDUCERS[name]()
    gm = _mixture(0)
    key = jax.random.key(1)

    def score(means):
        out = drive(reducer, gm._replace(means=means), key)[0]
        return jnp.sum(out.weights[:, None] * out.means**2) + jnp.sum(out.weights[:, None, None] * out.covs)

    g = np.asarray(jax.jit(jax.grad(score))(gm.means))
    assert np.all(np.isfinite(g))
    eps = 1e-6
    fd = np.zeros_like(g)
    s = jax.jit(score)
    for i in range(K):
        for j in range(2):
            fd[i, j] = (s(gm.means.at[i, j].add(eps)) - s(gm.means.at[i, j].add(-eps))) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6)


def test_threshold_change_does_not_recompile():
    traces = []

    def f(reducer, gm):
        traces.append(1)
        return drive(reducer, gm, None)[0].weights

    jf = jax.jit(f)
    gm = _mixture(0)
    jf(reduction.PruneThreshold(threshold=0.1), gm)
    jf(reduction.PruneThreshold(threshold=0.2), gm)
    jf(reduction.PCM(rho=0.9, newton_steps=2), gm)
    jf(reduction.PCM(rho=0.8, newton_steps=2), gm)
    assert len(traces) == 2


# ---------------------------------------------------------------------------------------------
# Filters: one generic driver for every filter of the package.

from gmjax import filters as F  # noqa: E402
from gmjax.models import simulate  # noqa: E402
from gmjax.scenarios import (
    manoeuvring_target,  # noqa: E402
    uwb_velocity,  # noqa: E402
)
from gmjax.scenarios.gamma_system import gamma_system  # noqa: E402
from gmjax.scenarios.jump_system import jump_system  # noqa: E402

N_STEPS = 8


def _jump():
    return jump_system()._replace(n_steps=N_STEPS)


def _linear():
    return uwb_velocity.synthetic(1, 1.0)._replace(n_steps=N_STEPS)


def _imm_filters(kind):
    def build(sc):
        models = manoeuvring_target.imm_models()
        if kind == "imm":
            return F.build_imm(models, manoeuvring_target.TRANSITION, filter="kf")
        return F.build_imm_gsf(
            models,
            manoeuvring_target.TRANSITION,
            local="kf",
            reducer=reduction.Runnalls(num_out=4, capacity=4),
            capacity=4,
        )

    return build


def _imm_scenario():
    return manoeuvring_target.circular_motion()._replace(n_steps=N_STEPS)


# name -> (scenario factory, filter factory, whether d(loglik)/d(params) is smooth)
FILTERS = {
    "kf": (_linear, lambda sc: F.build_kf(sc.model), True),
    "kalman_filter": (
        _linear,
        lambda sc: F.kalman_filter(
            np.array([[1.0, 1.0], [0.0, 1.0]]),
            np.array([[1.0, 0.0]]),
            np.eye(2),
            np.eye(1),
            np.zeros(2),
            10.0 * np.eye(2),
        ),
        True,
    ),
    "ekf": (_jump, lambda sc: F.build_ekf(sc.model), True),
    "ukf": (_jump, lambda sc: F.build_ukf(sc.model), True),
    "ckf": (_jump, lambda sc: F.build_ckf(sc.model), True),
    "ghkf": (_jump, lambda sc: F.build_ghkf(sc.model), True),
    "sgkf": (_jump, lambda sc: F.build_sgkf(sc.model), True),
    "sckf": (_jump, lambda sc: F.build_sckf(sc.model), True),
    "gsf_runnalls": (
        _jump,
        lambda sc: F.build_gsf(sc.model, "ekf", reduction.Runnalls(num_out=6), capacity=6),
        True,
    ),
    "gsf_gmrcm": (
        _jump,
        lambda sc: F.build_gsf(sc.model, "ukf", reduction.GMRCM(capacity=6, newton_steps=0), capacity=6),
        True,
    ),
    "imm": (_imm_scenario, _imm_filters("imm"), True),
    "imm_gsf": (_imm_scenario, _imm_filters("imm_gsf"), True),
    "agsf": (lambda: gamma_system()._replace(n_steps=N_STEPS), lambda sc: F.build_agsf(sc.model), True),
    "bank": (_linear, lambda sc: F.build_bank(sc.model, "red-gsfm"), True),
    "pf": (_jump, lambda sc: F.build_pf(sc.model, 64), False),
}
# the rest run with -m slow; each family's own test file checks its gradient and jit == eager
_FAST = {"kalman_filter", "ukf", "gsf_runnalls", "pf"}


def _scale_floats(tree, factor):
    """Every floating leaf of a params pytree times ``factor`` (a direction that keeps covariances PD)."""
    return jax.tree_util.tree_map(
        lambda a: a * factor if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else a, tree
    )


@pytest.mark.parametrize(
    "name", [n if n in _FAST else pytest.param(n, marks=pytest.mark.slow) for n in sorted(FILTERS)]
)
def test_every_filter_runs_through_the_one_driver(name):
    make_scenario, build, smooth = FILTERS[name]
    sc = make_scenario()
    filt = build(sc)
    assert isinstance(filt, F.Filter)
    keys = jax.random.split(jax.random.key(3), 2)
    zss = jnp.stack([simulate(sc, k)[1] for k in keys])
    if name == "kalman_filter":
        zss = zss[..., :1]
    key = jax.random.key(7)

    def driver(zs, params, key):
        return F.run(filt, zs, key=key, params=params)

    states, infos = driver(zss[0], filt.params, key)  # eager (the scan is traced once)
    assert isinstance(infos, F.StepInfo) and isinstance(infos.flags, F.StepFlags)
    d = infos.mean.shape[-1]
    assert infos.mean.shape == (N_STEPS, d) and infos.cov.shape == (N_STEPS, d, d)
    assert infos.loglik.shape == (N_STEPS,) and infos.n_components.dtype == jnp.int32
    assert np.all(np.isfinite(np.asarray(infos.mean))) and np.all(np.isfinite(np.asarray(infos.loglik)))
    # jit == eager
    jitted = jax.jit(driver)(zss[0], filt.params, key)[1]
    np.testing.assert_allclose(np.asarray(jitted.mean), np.asarray(infos.mean), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(jitted.loglik), np.asarray(infos.loglik), rtol=1e-9, atol=1e-9)
    # vmap over runs and over parameter sets == loop
    param_sets = [filt.params, _scale_floats(filt.params, 1.1)]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *param_sets)
    batched = jax.jit(jax.vmap(driver, in_axes=(0, 0, None)))(zss, stacked, key)[1]
    for i in range(2):
        one = jax.jit(driver)(zss[i], param_sets[i], key)[1]
        np.testing.assert_allclose(np.asarray(batched.mean[i]), np.asarray(one.mean), rtol=1e-9, atol=1e-9)

    # grad of the summed log-likelihood w.r.t. the whole params pytree, checked along a direction
    # that scales every floating leaf (noise covariances, means, weights, thresholds together)
    def total(eps):
        return jnp.sum(driver(zss[0], _scale_floats(filt.params, 1.0 + eps), key)[1].loglik)

    grads = jax.jit(jax.grad(lambda p: jnp.sum(driver(zss[0], p, key)[1].loglik), allow_int=True))(
        filt.params
    )
    for leaf in jax.tree_util.tree_leaves(grads):
        if jnp.issubdtype(jnp.asarray(leaf).dtype, jnp.floating):
            assert np.all(np.isfinite(np.asarray(leaf)))
    if smooth:  # a particle filter's loglik is piecewise (resampling) in its parameters
        g = float(jax.jit(jax.grad(total))(0.0))
        h = 1e-6
        fd = float((jax.jit(total)(h) - jax.jit(total)(-h)) / (2 * h))
        np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6)


def test_configs_of_different_classes_never_share_a_tree_structure():
    """Equal static fields, different algorithms: a jit cache must not mix them up (seen in CI)."""
    a = jax.tree_util.tree_structure(reduction.PruneTop(num_out=3))
    b = jax.tree_util.tree_structure(reduction.BruteForce(num_out=3))
    assert a != b
    gm = _mixture(0)
    f = jax.jit(lambda r, g: drive(r, g, None)[0].weights)
    np.testing.assert_allclose(
        f(reduction.BruteForce(num_out=3), gm),
        drive(reduction.BruteForce(num_out=3), gm, None)[0].weights,
        rtol=1e-10,
    )
    np.testing.assert_allclose(
        f(reduction.PruneTop(num_out=3), gm),
        drive(reduction.PruneTop(num_out=3), gm, None)[0].weights,
        rtol=1e-10,
    )
