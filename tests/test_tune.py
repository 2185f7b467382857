"""Relaxed reducers (mode / temperature of PruneThreshold, PruneCensored, PCM), the relaxation
primitives (gmjax.reduction.relax) and the tuning loop (gmjax.tune)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from gmjax import tune as T
from gmjax.filters import build_kf
from gmjax.filters.gsf import build_gsf
from gmjax.mixture import GaussianMixture, pad
from gmjax.models import Scenario, StateSpaceModel
from gmjax.reduction import PCM, PruneCensored, PruneThreshold, pcm, prune_censored, prune_threshold
from gmjax.reduction import relax as R
from gmjax.scenarios.jump_system import jump_system

K = 14  # one capacity throughout so compiled kernels are shared


def random_gm(seed, n=11, capacity=K, dtype=jnp.float64):
    rng = np.random.default_rng(seed)
    w = rng.dirichlet(np.ones(n))
    m = rng.normal(0.0, 3.0, (n, 1))
    P = rng.uniform(0.3, 2.0, (n, 1, 1))
    return GaussianMixture.create(w, m, P, capacity=capacity, dtype=dtype)


def assert_same(a, b):
    for name, x, y in zip(a._fields, a, b):
        assert jnp.array_equal(x, y), name


def central_fd(f, x, eps):
    x = jnp.asarray(x)
    cols = []
    for e in np.eye(x.size):
        e = jnp.asarray(e.reshape(x.shape), x.dtype)
        cols.append((f(x + eps * e) - f(x - eps * e)) / (2 * eps))
    return jnp.stack(cols)


# --------------------------------------------------------------------------- the relaxed step


def test_soft_step_modes_and_zero_temperature():
    x = jnp.asarray([-1.0, -1e-3, 0.0, 2e-3, 3.0])
    hard = np.array([0, 0, 1, 1, 1.0])
    strict = np.array([0, 0, 0, 1, 1.0])
    np.testing.assert_array_equal(R.soft_step(x, 0.0), hard)
    np.testing.assert_array_equal(R.soft_step(x, 0.0, strict=True), strict)
    np.testing.assert_array_equal(R.soft_step(x, 0.5, mode="hard"), hard)
    np.testing.assert_allclose(R.soft_step(x, 0.5), 1 / (1 + np.exp(-np.asarray(x) / 0.5)), rtol=1e-14)
    np.testing.assert_array_equal(R.soft_step(x, 0.5, mode="straight_through"), hard)
    # straight-through: hard value, sigmoid gradient; all gradients finite at T = 0
    g_st = jax.grad(lambda t: jnp.sum(R.soft_step(x - t, 0.5, mode="straight_through")))(0.1)
    g_soft = jax.grad(lambda t: jnp.sum(R.soft_step(x - t, 0.5)))(0.1)
    assert g_st == g_soft and g_soft < 0
    g0 = jax.grad(lambda tau: jnp.sum(R.soft_step(x, tau)))(0.0)
    assert np.isfinite(g0)
    with pytest.raises(ValueError, match="mode"):
        R.soft_step(x, 0.1, mode="fuzzy")


def test_soft_split_gate():
    from gmjax.filters.agsf import hard_gate

    assert T.soft_split_gate is R.soft_split_gate  # kept importable from gmjax.tune

    psi = jnp.asarray([0.1, 0.5, 0.9])
    hard = T.soft_split_gate(0.0)(psi, 0.5)
    np.testing.assert_array_equal(hard, [0.0, 1.0, 1.0])  # eq 31: split when ψ >= ψ_th
    np.testing.assert_array_equal(hard, hard_gate(psi, 0.5))
    soft = T.soft_split_gate(0.1)
    np.testing.assert_allclose(soft(psi, 0.5), 1 / (1 + np.exp(-(np.asarray(psi) - 0.5) / 0.1)), rtol=1e-14)
    st = T.soft_split_gate(0.1, mode="straight_through")
    np.testing.assert_array_equal(st(psi, 0.5), hard)
    g = jax.grad(lambda th: jnp.sum(st(psi, th)))(0.5)
    g_ref = central_fd(lambda th: jnp.sum(soft(psi, th)), jnp.asarray([0.5]), 1e-6)[0]
    np.testing.assert_allclose(g, g_ref, rtol=1e-7)
    with pytest.raises(ValueError, match="temperature"):
        T.soft_split_gate(-1.0)
    rel = T.soft_split_gate(0.25, relative=True)  # temperature in units of the threshold
    np.testing.assert_allclose(
        rel(psi, 0.4), 1 / (1 + np.exp(-(np.asarray(psi) / 0.4 - 1) / 0.25)), rtol=1e-14
    )
    np.testing.assert_array_equal(T.soft_split_gate(0.25, relative=True, mode="hard")(psi, 0.5), hard)


# --------------------------------------------------------------------------- soft pruning


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_soft_pruning_at_zero_temperature_is_hard(dtype):
    for seed in range(3):
        gm = random_gm(seed, dtype=dtype)
        for rho, nu in ((0.9544, None), (0.8, 6), (0.3, None)):
            a, ia = prune_censored(gm, rho, nu)
            for mode in ("soft", "hard", "straight_through"):
                red = PruneCensored(rho, nu, temperature=0.0 if mode == "soft" else 0.05, mode=mode)
                b, ib = red(gm)
                assert_same(a, b)
                assert jnp.array_equal(ia.labels, ib.labels) and ia.pruned_mass == ib.pruned_mass
                b2, _ = prune_censored(gm, rho, nu, temperature=red.temperature, mode=mode)  # functional form
                assert_same(a, b2)
        a, ia = prune_threshold(gm, 0.05)
        b, _, ib = PruneThreshold(0.05, temperature=0.0, mode="soft").reduce(gm, None)
        assert_same(a, b)
        assert jnp.array_equal(ia.labels, ib.labels)


def test_censored_gates_match_the_order_statistic_rule():
    """Independent check: a plain loop over eqs 19–22 (ascending sort, gamma_n, n_max)."""
    gm = random_gm(4)
    w = np.asarray(gm.weights)[np.asarray(gm.mask)]
    for rho in (0.5, 0.9, 0.9544, 0.99):
        asc = np.sort(w)
        I = len(asc)
        gamma = [asc[n:].sum() / asc.sum() for n in range(I)]  # share of the I - n largest (eq 20)
        n_max = max(n for n in range(I) if gamma[n] >= rho)  # eq 21 (0-based n)
        N = I - n_max  # eq 22 without a cap
        g = np.asarray(R.censored_gates(gm, rho, 0.0))
        assert g.sum() == N
        kept = np.asarray(gm.weights)[g > 0]
        assert kept.min() >= np.sort(w)[::-1][N - 1]


def test_soft_pruning_gradients_match_finite_differences():
    gm = random_gm(1)

    def f(theta):
        out, info = PruneCensored(theta[0], 8, temperature=0.03, mode="soft")(gm)
        return jnp.sum(out.weights * out.means[:, 0]) + info.aux["n_expected"]

    theta = jnp.asarray([0.9])
    g = jax.grad(f)(theta)
    np.testing.assert_allclose(g, central_fd(f, theta, 1e-6), rtol=1e-6, atol=1e-9)
    assert abs(float(g[0])) > 0

    def h(th):
        out, _ = prune_threshold(gm, th[0], temperature=0.01, mode="soft")
        return jnp.sum(out.weights * out.means[:, 0] ** 2)

    th = jnp.asarray([0.06])
    np.testing.assert_allclose(jax.grad(h)(th), central_fd(h, th, 1e-7), rtol=1e-6, atol=1e-9)


def test_straight_through_pruning():
    gm = random_gm(2)
    a, _ = prune_censored(gm, 0.9)

    def f(rho, mode):
        out, _ = PruneCensored(rho, temperature=0.05, mode=mode)(gm)
        return out

    b = f(0.9, "straight_through")
    assert_same(a, b)  # hard forward pass
    g = jax.grad(lambda r: jnp.sum(f(r, "straight_through").weights * f(r, "straight_through").means[:, 0]))(
        0.9
    )
    assert np.isfinite(g) and g != 0


# --------------------------------------------------------------------------- soft PCM


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_soft_pcm_at_zero_temperature_is_pcm(dtype):
    for seed in range(3):
        gm = random_gm(10 + seed, dtype=dtype)
        for rho, lam in ((0.9544, 2.0), (0.99, 1.37), (0.9, 2.9)):  # traced: one compilation
            a, ia = pcm(gm, rho=rho, lam=lam, max_components=8)
            modes = (("soft", (0.0, 0.0)), ("hard", (0.05, 0.25)), ("straight_through", (0.05, 0.25)))
            for mode, temps in modes[: 3 if dtype == jnp.float64 else 1]:
                b, ib = PCM(
                    rho=rho,
                    lam=lam,
                    max_components=8,
                    gate_temperature=temps[0],
                    temperature=temps[1],
                    grid_size=9,
                    mode=mode,
                )(gm)
                assert_same(a, b)
                assert jnp.array_equal(ia.labels, ib.labels)
                assert ia.cost == ib.cost and ia.pruned_mass == ib.pruned_mass
                # the relaxed modes report the expected output size (hard mode: PCM's own aux)
                assert ib.aux["n_expected" if mode != "hard" else "n_clusters"] == ia.aux["n_clusters"]


def test_soft_membership_is_the_search_relaxation():
    gm = random_gm(5)
    grid = jnp.linspace(1.0, 3.0, 9)
    A, pi, grid_labels, labels = R.soft_membership(gm, 2.1, grid, 0.25)
    live = np.asarray(gm.mask)
    np.testing.assert_allclose(np.asarray(A).sum(1)[live], 1.0, rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(A)[~live], 0.0)
    w = np.exp(-0.5 * ((2.1 - np.asarray(grid)) / 0.25) ** 2)
    np.testing.assert_allclose(pi, w / w.sum(), rtol=1e-12)
    # A(λ) is the π-average of the grid's one-hot clusterings (plain loop)
    A_ref = np.zeros((K, K))
    for g in range(9):
        for m, c in enumerate(np.asarray(grid_labels[g])):
            if c >= 0:
                A_ref[m, c] += pi[g]
    np.testing.assert_allclose(A, A_ref, rtol=1e-12)
    A0, _, _, labels0 = R.soft_membership(gm, 2.1, grid, 0.0)
    onehot = (np.asarray(labels0)[:, None] == np.arange(K)[None]).astype(float)
    np.testing.assert_array_equal(A0, onehot)


def _soft_pcm_objective():
    gm = random_gm(3)

    def f(theta):
        out, info = pcm(
            gm,
            rho=theta[0],
            lam=theta[1],
            max_components=9,
            gate_temperature=0.02,
            temperature=0.25,
            grid_size=9,
            mode="soft",
        )
        return (
            jnp.sum(out.weights * out.means[:, 0] ** 2)
            + jnp.sum(out.weights * out.covs[:, 0, 0])
            + 10 * info.cost
            + 0.1 * info.aux["n_expected"]
        )

    return f, jnp.asarray([0.93, 2.1])


def test_soft_pcm_gradients_match_finite_differences():
    f, theta = _soft_pcm_objective()
    g_fwd = jax.jacfwd(f)(theta)
    np.testing.assert_allclose(g_fwd, central_fd(f, theta, 1e-6), rtol=1e-6, atol=1e-8)
    assert np.all(np.abs(np.asarray(g_fwd)) > 0)


@pytest.mark.slow
def test_soft_pcm_reverse_mode_equals_forward_mode():
    f, theta = _soft_pcm_objective()
    np.testing.assert_allclose(jax.grad(f)(theta), jax.jacfwd(f)(theta), rtol=1e-10)


def test_soft_pcm_gradient_finite_with_negligible_weights():
    """A soft gate keeps a 1e-160 component live; merged alone, its squared weight would underflow
    in the derivative (regression: a NaN gradient seen while tuning the PCM-GSF)."""
    w = np.array([0.5, 0.3, 0.2 - 1e-12, 1e-12, 1e-80, 1e-160])
    gm = GaussianMixture.create(
        w, [[0.0], [1.0], [2.5], [6.0], [-9.0], [14.0]], np.ones((6, 1, 1)), capacity=K
    )

    def f(theta):
        out, info = pcm(
            gm, rho=theta[0], lam=theta[1], gate_temperature=0.02, temperature=0.25, grid_size=9, mode="soft"
        )
        return jnp.sum(out.weights * out.means[:, 0]) + jnp.sum(out.covs) + info.cost

    g = jax.jacfwd(f)(jnp.asarray([0.99, 2.0]))
    assert np.all(np.isfinite(np.asarray(g)))
    out, _ = pcm(gm, rho=0.99, lam=2.0, gate_temperature=0.02, temperature=0.25, grid_size=9, mode="soft")
    assert float(jnp.min(jnp.where(out.mask, out.weights, 1.0))) > 1e-40


def test_soft_pcm_jit_vmap_padding():
    cfg = PCM(
        rho=0.95, lam=1.8, gate_temperature=0.02, temperature=0.25, max_components=9, grid_size=9, mode="soft"
    )
    gms = [random_gm(20 + s) for s in range(3)]
    eager = [cfg(g) for g in gms]
    jitted = jax.jit(lambda c, g: c(g))(cfg, gms[0])
    for x, y in zip(jitted[0], eager[0][0]):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-14)
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gms)
    batched, binfo = jax.vmap(lambda g: cfg(g))(stacked)
    for i, (out, info) in enumerate(eager):
        for x, y in zip(out, jax.tree_util.tree_map(lambda a: a[i], batched)):
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(info.cost, binfo.cost[i], rtol=1e-12)
    # extra padded slots change nothing (capacity of the output fixed)
    padded = pad(gms[0], K + 4)
    out_p, info_p = pcm(
        padded,
        rho=0.95,
        lam=1.8,
        gate_temperature=0.02,
        temperature=0.25,
        grid_size=9,
        max_components=9,
        capacity=9,
        mode="soft",
    )
    out_0, info_0 = eager[0]
    n0 = int(out_0.mask.sum())
    assert int(out_p.mask.sum()) == n0
    np.testing.assert_allclose(out_p.weights[:n0], out_0.weights[:n0], rtol=1e-12)
    np.testing.assert_allclose(out_p.means[:n0], out_0.means[:n0], rtol=1e-12)
    np.testing.assert_allclose(info_p.cost, info_0.cost, rtol=1e-12)


def test_soft_pcm_validation():
    gm = random_gm(0)
    soft = dict(lam=2.0, mode="soft", grid_size=9)
    with pytest.raises(ValueError, match="rho"):
        pcm(gm, rho=1.5, **soft)
    with pytest.raises(ValueError, match="temperature"):
        pcm(gm, temperature=-0.1, **soft)
    with pytest.raises(ValueError, match="gate_temperature"):
        pcm(gm, gate_temperature=-0.1, **soft)
    with pytest.raises(ValueError, match="mode"):
        pcm(gm, lam=2.0, mode="warm")
    with pytest.raises(ValueError, match="lambda_range"):
        pcm(gm, lambda_range=(3.0, 1.0), **soft)
    with pytest.raises(ValueError, match="lam"):  # the relaxed modes need a fixed λ
        pcm(gm, mode="soft")
    with pytest.raises(ValueError, match="temperature"):  # the search still needs τ > 0
        pcm(gm, temperature=0.0)
    pcm(gm, temperature=0.0, **soft)  # at a fixed λ, τ = 0 is the hard clustering
    with pytest.raises(ValueError, match="mode"):
        PruneThreshold(0.01, mode="fuzzy")(gm)
    with pytest.raises(ValueError, match="temperature"):
        PruneCensored(0.9, temperature=-1.0, mode="soft")(gm)


def test_soft_pcm_without_pruning_and_moment_merge():
    """prune=False and merge="moment" in the relaxed mode: zero temperatures equal the hard PCM."""
    gm = random_gm(6)
    for merge in ("ci", "moment"):
        a, ia = pcm(gm, lam=1.9, prune=False, merge=merge)
        b, ib = pcm(gm, lam=1.9, prune=False, merge=merge, temperature=0.0, mode="soft")
        assert_same(a, b)
        assert jnp.array_equal(ia.labels, ib.labels) and ia.cost == ib.cost
        out, info = pcm(gm, lam=1.9, prune=False, merge=merge, temperature=0.25, mode="soft")
        np.testing.assert_allclose(jnp.sum(out.weights), jnp.sum(gm.weights), rtol=1e-12)  # weight kept
        assert float(info.aux["n_pruned_expected"]) == int(gm.mask.sum())


# --------------------------------------------------------------------------- the tuning loop


def random_walk(q_true=1.0, r=1.0, p0=4.0, n_steps=25):
    """Scalar random walk observed in Gaussian noise; ``model_q`` builds the filter's model."""

    def model_q(q):
        dtype = jnp.float64
        one = lambda v: GaussianMixture(  # noqa: E731
            jnp.ones(1, dtype),
            jnp.zeros((1, 1), dtype),
            jnp.reshape(jnp.asarray(v, dtype), (1, 1, 1)),
            jnp.ones(1, bool),
        )
        return StateSpaceModel(
            f=lambda x, t: x, h=lambda x, t: x, process_noise=one(q), measurement_noise=one(r), prior=one(p0)
        )

    sc = Scenario(
        name="walk",
        model=model_q(q_true),
        n_steps=n_steps,
        sample_initial=lambda k: math.sqrt(p0) * jax.random.normal(k, (1,), jnp.float64),
        sample_process_noise=lambda k, t: math.sqrt(q_true) * jax.random.normal(k, (1,), jnp.float64),
        sample_measurement_noise=lambda k, t: math.sqrt(r) * jax.random.normal(k, (1,), jnp.float64),
    )
    return sc, model_q


def expected_armse(q_hat, q_true=1.0, r=1.0, p0=4.0, n_steps=25):
    """Closed form: exact error variance of a Kalman filter that assumes ``q_hat`` (plain loop)."""
    P = S = p0
    out = []
    for _ in range(n_steps):
        Pm, Sm = P + q_hat, S + q_true
        Kg = Pm / (Pm + r)
        P = (1 - Kg) * Pm
        S = (1 - Kg) ** 2 * Sm + Kg**2 * r
        out.append(math.sqrt(S))
    return float(np.mean(out))


def test_tune_recovers_the_optimal_kalman_gain():
    """Tuning q of a Kalman filter on ARMSE lands where the exact expected ARMSE is minimal.

    The minimiser of the common-random-numbers objective differs from the true q by sampling error;
    the criterion is that the exact expected ARMSE at the tuned q exceeds the optimum (at q_true) by
    less than 2 Monte Carlo standard errors of the ARMSE estimate, while the start is far worse.
    """
    sc, model_q = random_walk()
    n_runs = 256
    res = T.tune(
        lambda p: build_kf(model_q(p["q"])),
        sc,
        {"q": 0.1},
        T.armse_loss(),
        optimizer=optax.adam(0.2),
        n_runs=n_runs,
        steps=40,
        key=jax.random.key(3),
        bounds={"q": (1e-3, 20.0)},
        resample=False,
        progress=False,
    )
    h = res.history
    assert h.ok.all() and h.loss.shape == (40,) and h.params["q"][0] == pytest.approx(0.1)
    assert h.loss[-1] < h.loss[0]
    sq_at = jax.jit(lambda q: T.study_scores(build_kf(model_q(q)), sc, n_runs, jax.random.key(3)).sq_error)
    # Monte Carlo standard error of the ARMSE (delta method over runs) at the tuned q
    sq = np.asarray(sq_at(res.params["q"]))
    rmse = np.sqrt(sq.mean(0))
    per_run = (sq / (2 * sq.shape[1] * rmse)).sum(1)
    se = per_run.std(ddof=1) / math.sqrt(n_runs)
    best = expected_armse(1.0)
    assert expected_armse(res.params["q"]) - best < 2 * se
    assert expected_armse(0.1) - best > 10 * se
    # the recorded gradient is d loss / d q of the same objective (finite differences)
    q = h.params["q"][-1]
    f = lambda v: jnp.mean(jnp.sqrt(jnp.mean(sq_at(v[0]), axis=0)))  # noqa: E731  (the ARMSE)
    np.testing.assert_allclose(
        h.grads["q"][-1], central_fd(f, jnp.asarray([q]), 1e-5)[0], rtol=1e-5, atol=1e-8
    )


def test_losses_and_bounds():
    scores = T.TuneScores(
        sq_error=jnp.asarray([[1.0, 4.0], [9.0, 16.0]]),
        position_sq_error=jnp.asarray([[1.0, 4.0], [9.0, 16.0]]),
        nees=jnp.asarray([[1.0, 2.0], [3.0, 4.0]]),
        cost=jnp.asarray([[0.1, 0.2], [0.3, 0.4]]),
        n_expected=jnp.asarray([[2.0, 3.0], [4.0, 5.0]]),
        flags=jnp.zeros((2, 2), bool),
    )
    armse = (math.sqrt(5.0) + math.sqrt(10.0)) / 2
    assert float(T.armse_loss()(scores)) == pytest.approx(armse)
    assert float(T.anees_loss(1.0)(scores)) == pytest.approx(1.5)
    assert float(T.aeise_loss()(scores)) == pytest.approx(0.25)
    assert float(T.count_loss()(scores)) == pytest.approx(3.5)
    w = T.weighted_loss((1.0, T.armse_loss()), (0.5, T.count_loss()))
    assert float(w(scores)) == pytest.approx(armse + 1.75)
    for b, x in (
        (T.Bounds(0.5, 0.9999), 0.9544),
        (T.Bounds(1.0, None), 2.5),
        (T.Bounds(None, 3.0), -1.0),
        (T.Bounds(), 0.3),
        (T.Bounds(1e-3, 20.0, log=True), 0.02),
    ):
        assert float(b.to_constrained(jnp.asarray(b.to_unconstrained(x)))) == pytest.approx(x, rel=1e-12)
    with pytest.raises(ValueError, match="terms"):
        T.weighted_loss()


def test_tune_validation():
    sc, model_q = random_walk()
    fac = lambda p: build_kf(model_q(p["q"]))  # noqa: E731
    kw = dict(key=jax.random.key(0), progress=False)
    with pytest.raises(ValueError, match=r"params0\['q'\]"):
        T.tune(fac, sc, {"q": 30.0}, T.armse_loss(), bounds={"q": (0.0, 20.0)}, **kw)
    with pytest.raises(ValueError, match="bounds"):
        T.tune(fac, sc, {"q": 1.0}, T.armse_loss(), bounds={"r": (0.0, 2.0)}, **kw)
    with pytest.raises(ValueError, match="ad"):
        T.tune(fac, sc, {"q": 1.0}, T.armse_loss(), ad="sideways", **kw)
    with pytest.raises(ValueError, match="n_runs"):
        T.tune(fac, sc, {"q": 1.0}, T.armse_loss(), n_runs=0, **kw)


def _pcm_gsf(sc, p, mode="soft"):
    red = PCM(
        rho=p["rho"],
        lam=p["lam"],
        gate_temperature=0.02,
        temperature=0.25,
        grid_size=9,
        max_components=8,
        capacity=8,
        mode=mode,
    )
    return build_gsf(sc.model, "ekf", red, capacity=8, track_ise=False)


def test_pcm_gsf_study_gradient_matches_finite_differences():
    """The whole Monte Carlo loss of the relaxed PCM-GSF is differentiable in (ρ, λ)."""
    sc = jump_system(n_steps=8)
    loss = T.weighted_loss((1.0, T.armse_loss()), (0.01, T.count_loss()), (10.0, T.aeise_loss()))

    @jax.jit
    def f(theta):
        return loss(
            T.study_scores(_pcm_gsf(sc, {"rho": theta[0], "lam": theta[1]}), sc, 3, jax.random.key(7))
        )

    theta = jnp.asarray([0.95, 2.05])
    g = jax.jit(jax.jacfwd(f))(theta)
    np.testing.assert_allclose(g, central_fd(f, theta, 1e-6), rtol=1e-4, atol=1e-7)
    assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.slow
def test_pcm_gsf_reverse_mode_equals_forward_mode():
    sc = jump_system(n_steps=8)

    def f(theta):
        return T.armse_loss()(
            T.study_scores(_pcm_gsf(sc, {"rho": theta[0], "lam": theta[1]}), sc, 3, jax.random.key(7))
        )

    theta = jnp.asarray([0.95, 2.05])
    np.testing.assert_allclose(jax.jit(jax.grad(f))(theta), jax.jit(jax.jacfwd(f))(theta), rtol=1e-8)


@pytest.mark.slow
def test_pcm_gsf_hard_mode_equals_pcm_gsf():
    """At zero temperature the relaxed PCM-GSF is the PCM-GSF with a fixed λ, run for run."""
    sc = jump_system(n_steps=10)
    soft = build_gsf(
        sc.model,
        "ekf",
        PCM(
            rho=0.95,
            lam=2.0,
            max_components=8,
            capacity=8,
            gate_temperature=0.0,
            temperature=0.0,
            grid_size=9,
            mode="soft",
        ),
        capacity=8,
        track_ise=False,
    )
    hard = build_gsf(
        sc.model, "ekf", PCM(rho=0.95, lam=2.0, max_components=8, capacity=8), capacity=8, track_ise=False
    )
    a = T.study_scores(soft, sc, 4, jax.random.key(1))
    b = T.study_scores(hard, sc, 4, jax.random.key(1))
    np.testing.assert_array_equal(a.sq_error, b.sq_error)
    np.testing.assert_array_equal(a.cost, b.cost)


# --------------------------------------------------------------------------- relaxed reducers inside filter.params


def _pruned_gsf(n_steps=8):
    """A GSF whose reducer is the relaxed censored pruning; ρ is a leaf of ``filter.params``."""
    sc = jump_system(n_steps=n_steps)
    red = PruneCensored(0.9, 8, temperature=0.03, mode="soft")
    return sc, build_gsf(sc.model, "ekf", red, capacity=8, track_ise=False)


def _with(filt, rho=None, q_var=None):
    """``filt.params`` with the reducer's ``ρ`` and / or the first process-noise variance replaced."""
    import dataclasses

    p = filt.params
    if rho is not None:
        p = p._replace(reducer=dataclasses.replace(p.reducer, rho=rho))
    if q_var is not None:
        q = p.model.process_noise
        p = p._replace(model=p.model._replace(process_noise=q._replace(covs=q.covs.at[0, 0, 0].set(q_var))))
    return p


def test_loglik_gradient_through_filter_params():
    """d Σ loglik / d (ρ, Q[0]) through ``run``, both leaves of ``filter.params``: central differences."""
    from gmjax.filters import run
    from gmjax.filters.base import StepInputs
    from gmjax.models import simulate

    sc, filt = _pruned_gsf()
    _, zs, ts = simulate(sc, jax.random.key(5))
    q0 = float(filt.params.model.process_noise.covs[0, 0, 0])

    @jax.jit
    def f(theta):
        _, infos = run(filt, zs, StepInputs(t=ts), params=_with(filt, rho=theta[0], q_var=theta[1]))
        return jnp.sum(infos.loglik)

    theta = jnp.asarray([0.9, q0])
    g = jax.grad(f)(theta)
    assert np.all(np.isfinite(np.asarray(g))) and abs(float(g[0])) > 0
    np.testing.assert_allclose(g, central_fd(f, theta, 1e-6), rtol=1e-5, atol=1e-8)


@pytest.mark.slow
def test_study_scores_over_params_jit_equals_eager():
    """``study_scores(..., params=)`` equals rebuilding the filter; jit equals eager."""
    sc, filt = _pruned_gsf(n_steps=6)
    p = _with(filt, rho=0.8)
    red = PruneCensored(0.8, 8, temperature=0.03, mode="soft")
    rebuilt = build_gsf(sc.model, "ekf", red, capacity=8, track_ise=False)
    eager = T.study_scores(filt, sc, 2, jax.random.key(2), params=p)
    jitted = jax.jit(lambda q: T.study_scores(filt, sc, 2, jax.random.key(2), params=q))(p)
    ref = T.study_scores(rebuilt, sc, 2, jax.random.key(2))
    for name, a, b, c in zip(eager._fields, eager, jitted, ref):
        if a is None:  # an optional score this filter does not report
            assert b is None and c is None, name
            continue
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(a, c, rtol=1e-12, atol=1e-14)
    assert eager.n_expected.shape == (2, 6)  # the gated pruning's expected survivors


def test_tune_over_a_leaf_of_filter_params():
    """``tune`` with a factory that replaces a leaf of ``filter.params``: the recorded gradient is the
    study's gradient (common random numbers)."""
    sc, filt = _pruned_gsf(n_steps=6)
    factory = lambda p: filt._replace(params=_with(filt, rho=p["rho"]))  # noqa: E731
    res = T.tune(
        factory,
        sc,
        {"rho": 0.9},
        T.armse_loss(),
        optimizer=optax.sgd(1e-3),
        n_runs=2,
        steps=2,
        key=jax.random.key(4),
        bounds={"rho": (0.5, 0.9999)},
        resample=False,
        progress=False,
    )
    assert res.history.ok.all() and res.history.params["rho"][0] == pytest.approx(0.9)
    f = jax.jit(lambda v: T.armse_loss()(T.study_scores(factory({"rho": v[0]}), sc, 2, jax.random.key(4))))
    g = jax.grad(f)(jnp.asarray([0.9]))
    np.testing.assert_allclose(res.history.grads["rho"][0], g[0], rtol=1e-8)
    assert np.isfinite(res.history.loss).all()

    # the same tuning named by the leaf of filter.params (the params way, as gmjax.fit): same steps
    kw = dict(
        optimizer=optax.sgd(1e-3), n_runs=2, steps=2, key=jax.random.key(4), resample=False, progress=False
    )
    by_leaf = T.tune(
        filt, sc, {"reducer.rho": 0.9}, T.armse_loss(), bounds={"reducer.rho": (0.5, 0.9999)}, **kw
    )
    np.testing.assert_allclose(by_leaf.history.loss, res.history.loss, rtol=1e-12)
    np.testing.assert_allclose(by_leaf.history.grads["reducer.rho"], res.history.grads["rho"], rtol=1e-10)
    assert by_leaf.params["reducer.rho"] == pytest.approx(res.params["rho"], rel=1e-12)
    with pytest.raises(ValueError, match="params0: 'reducer.nope' names no floating leaf"):
        T.tune(filt, sc, {"reducer.nope": 0.9}, T.armse_loss(), **kw)
    with pytest.raises(ValueError, match="params0: .*shape"):
        T.tune(filt, sc, {"model.process_noise.covs": 1.0}, T.armse_loss(), **kw)
