"""gmjax.reduction.eise.newton: Newton's early-exit loops against the fixed-length scan (values and both
modes of derivatives), the batching rules, and a plain NumPy Newton loop."""

import importlib
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmjax.mixture import GaussianMixture
from gmjax.reduction.eise import (
    ConfidenceSearch,
    hard_eise,
    search_confidence,
)

# the search's parts, by module (the package `gmjax.reduction` exports a function named `eise`)
eise_relaxed = importlib.import_module("gmjax.reduction.eise.relaxed")
eise_newton = importlib.import_module("gmjax.reduction.eise.newton")

from eise_cases import CASES, K, _grid_for, case, random_gm


@jax.jit
def _newton_problem(gm, alpha=0.01):
    """Newton's inputs as :func:`search_confidence` builds them, from the grid's best ``λ``."""
    grid, labels, counts = _grid_for(gm)
    parts = eise_relaxed._relaxed_parts(gm, grid, labels, counts, "ci")
    lam0 = grid[jnp.argmin(jax.vmap(lambda lab: hard_eise(gm, lab, alpha=alpha)[0])(labels))]
    return (parts, jnp.asarray(0.2), jnp.asarray(alpha)), lam0


def _newton_early_and_fixed():
    """Nine Newton problems stacked (6 random mixtures, the static cases) and Newton on them two
    ways: ``early`` (``while_loop``s, the custom JVP) and ``fixed`` (the 8-step ``scan``)."""
    options = dict(method="ci", regularizer="exp", ise_scale=0.5)
    fun = partial(eise_relaxed._relaxed_at, **options)
    slopes = partial(eise_relaxed._relaxed_value_and_slopes, **options)  # as search_confidence takes them
    problems = [_newton_problem(random_gm(s, n=10)[0]) for s in range(6)] + [
        _newton_problem(case(name)) for name in CASES
    ]
    args = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[p[0] for p in problems])
    lam0 = jnp.stack([p[1] for p in problems])
    bounds = (1.0, 3.0)

    def early(args, lam0):
        return eise_newton._newton(fun, args, lam0, *bounds, 8, 1e-6, args[1], slopes=slopes)

    def fixed(args, lam0):
        return eise_newton._newton_loop(slopes, 8, 4, False, args, lam0, *bounds, 1e-6, args[1])

    return args, lam0, early, fixed


def _lam_of(f, temperature, alpha, parts, lam0):
    return f((parts, temperature, alpha), lam0)[0]


def _batched_derivative(derivative, args, lam0):
    """``derivative`` of ``λ(τ, α)`` at ``τ = 0.2, α = 0.01``, per problem."""
    return jax.jit(jax.vmap(derivative, in_axes=(None, None, 0, 0)))(
        jnp.asarray(0.2), jnp.asarray(0.01), args[0], lam0
    )


def _assert_same_derivative(ours, scan):
    # the same derivative; the custom JVP's instantiated zero tangents only reorder rounding
    assert np.all(np.isfinite(scan))
    np.testing.assert_allclose(ours, scan, rtol=1e-10, atol=1e-14 * float(np.max(np.abs(scan))))


def test_newton_early_exit_equals_the_fixed_scan():
    """Newton stops once every run is done (``while_loop``s) and returns exactly what the fixed
    8-step ``scan`` returns, alone and under vmap. Derivatives: the slow tests below (forward and
    reverse mode against the scan's), and in the default suite the 1-D search's ``jax.grad`` (the
    transpose of the custom JVP) against finite differences
    (``test_search_in_1d_gradient_matches_finite_differences``)."""
    args, lam0, early, fixed = _newton_early_and_fixed()
    batched_early, batched_fixed = jax.jit(jax.vmap(early))(args, lam0), jax.jit(jax.vmap(fixed))(args, lam0)
    for a, b in zip(batched_early, batched_fixed):
        np.testing.assert_array_equal(a, b)
    iterations = np.asarray(batched_early[3])
    assert iterations.min() < iterations.max() <= 8  # runs stop at different steps
    one = jax.tree_util.tree_map(lambda a: a[0], args)
    for a, b in zip(jax.jit(early)(one, lam0[0]), batched_fixed):
        np.testing.assert_array_equal(a, b[0])
    # the primal is a while_loop; only the derivative runs the scan
    assert "while" in str(jax.make_jaxpr(early)(one, lam0[0])) and "scan" not in str(
        jax.make_jaxpr(early)(one, lam0[0])
    )


@pytest.mark.slow  # two forward-mode programs through the scan: about 30 s of compiling
def test_newton_early_exit_differentiates_like_the_fixed_scan_in_forward_mode():
    """The forward-mode derivative of Newton's early exit (a custom JVP through the fixed ``scan``)
    equals the scan's own."""
    args, lam0, early, fixed = _newton_early_and_fixed()

    def forward(f):  # d λ / d τ
        return lambda t, a, p, l: jax.jvp(lambda t_: _lam_of(f, t_, a, p, l), (t,), (jnp.ones_like(t),))[1]

    _assert_same_derivative(*(_batched_derivative(forward(f), args, lam0) for f in (early, fixed)))


def test_newton_steps_only_the_runs_still_stepping_in_a_large_batch():
    """Under vmap over more than ``2 _STEP_CHUNK_MIN`` runs each Newton pass gathers the runs still
    stepping and steps them in chunks (:func:`eise.newton._step_until_done`): every run's result is
    bitwise the fixed ``scan``'s, with per-run ``τ, α`` and with ``τ, α`` the batch shares (as
    :func:`search_confidence` under vmap passes them: constants to XLA)."""
    args, lam0, early, fixed = _newton_early_and_fixed()
    n = 2 * eise_newton._STEP_CHUNK_MIN + 40
    reps = -(-n // lam0.shape[0])
    big_args = jax.tree_util.tree_map(lambda a: jnp.concatenate([a] * reps)[:n], args)
    shifts = np.repeat(np.linspace(-0.15, 0.15, reps), lam0.shape[0])[:n]
    big_lam0 = jnp.clip(jnp.concatenate([lam0] * reps)[:n] + shifts, 1.0, 3.0)

    def shared(newton):  # τ and α the batch shares
        return lambda parts, lam: newton((parts, jnp.asarray(0.2), jnp.asarray(0.01)), lam)

    for make in (lambda f: f, shared):
        operands = (big_args if make is not shared else big_args[0], big_lam0)
        got, want = (jax.jit(jax.vmap(make(f)))(*operands) for f in (early, fixed))
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
        iterations = np.asarray(got[3])
        # runs stop at different passes, and fewer than a quarter of them step to the end
        assert iterations.min() <= 2 and iterations.max() >= 4
        assert np.sum(iterations == iterations.max()) < n // 4


@pytest.mark.slow  # two reverse-mode programs through the scan: about a minute of compiling
def test_newton_early_exit_differentiates_like_the_fixed_scan_in_reverse_mode():
    """``jax.grad`` through Newton's early exit (the transpose of its custom JVP) equals the fixed
    ``scan``'s reverse-mode derivatives in ``τ`` and ``α``."""
    args, lam0, early, fixed = _newton_early_and_fixed()
    reverse = [
        _batched_derivative(jax.grad(partial(_lam_of, f), argnums=(0, 1)), args, lam0) for f in (early, fixed)
    ]
    for d_early, d_fixed in zip(*reverse):
        _assert_same_derivative(d_early, d_fixed)


def _newton_loop_numpy(f, lam, lo, hi, steps=8, tol=1e-9, radius=0.2, n_backtrack=4):
    """:func:`eise.newton._newton`'s rule as a plain loop that evaluates ``f(λ) -> (value, f', f'')`` at
    every ``λ`` it moves to; returns ``(λ, f(λ), converged, iterations, halvings)``."""
    value, g, h = f(lam)
    ok, halvings = False, 0
    for it in range(1, steps + 1):
        finite = np.isfinite(g) and np.isfinite(h)
        raw = g / h if finite and h > 0 else np.sign(g) * radius
        flat = abs(g) * radius <= 64 * np.finfo(float).eps * abs(value)
        raw = float(np.clip(raw, -radius, radius)) if finite and not flat else 0.0
        found, new = finite and raw == 0, (lam, value)
        for k in range(n_backtrack + 1):
            if found:
                break
            cand = float(np.clip(lam - raw * 0.5**k, lo, hi))
            found, new = f(cand)[0] <= value, (cand, f(cand)[0])
            halvings += k > 0 and found
        if not found:
            return lam, value, False, it, halvings
        ok = abs(new[0] - lam) < tol or abs(value - new[1]) <= tol * abs(value)
        lam = new[0]
        value, g, h = f(lam)
        if ok:
            return lam, value, True, it, halvings
    return lam, value, ok, steps, halvings


def _narrow_well(lam, args):
    """A narrow well: outside ±width the curvature is negative, so Newton's full step overshoots."""
    centre, width = args
    return -jnp.exp(-0.5 * ((lam - centre) / width) ** 2)


def _narrow_well_numpy(centre, width):
    def f(lam):
        u = (lam - centre) / width
        e = np.exp(-0.5 * u**2)
        return -e, e * u / width, e * (1 - u**2) / width**2

    return f


def _check_newton_against_the_numpy_loop(centres, widths, lam0):
    """Newton on the narrow wells, alone, under vmap and in the fixed ``scan``, against the plain
    loop; returns the loop's results."""
    expected = [
        _newton_loop_numpy(_narrow_well_numpy(c, w), l, 1.0, 3.0) for c, w, l in zip(centres, widths, lam0)
    ]
    newton = lambda args, lam: eise_newton._newton(_narrow_well, args, lam, 1.0, 3.0, 8, 1e-9, 0.2)  # noqa: E731
    fixed = lambda args, lam: eise_newton._newton_loop(  # noqa: E731
        partial(eise_newton._jvp_slopes, _narrow_well), 8, 4, False, args, lam, 1.0, 3.0, 1e-9, 0.2
    )
    args = (jnp.asarray(centres), jnp.asarray(widths))
    batched = [jax.jit(jax.vmap(f))(args, jnp.asarray(lam0)) for f in (newton, fixed)]
    alone = jax.jit(newton)
    for i, (lam, value, ok, iterations, _) in enumerate(expected):
        one = alone((args[0][i], args[1][i]), lam0[i])
        for got in (one, *(tuple(a[i] for a in b) for b in batched)):
            np.testing.assert_allclose(float(got[0]), lam, rtol=1e-12)
            np.testing.assert_allclose(float(got[1]), value, rtol=1e-12)
            assert bool(got[2]) == ok and int(got[3]) == iterations
    return expected


def test_newton_takes_the_derivatives_of_a_halved_candidate():
    """Where the full step overshoots, Newton halves it, and the next step starts from the halved
    candidate's derivatives (evaluated with its value): the iterates of a plain loop that evaluates
    the derivatives afresh wherever it moves, alone, under vmap and in the fixed ``scan``."""
    centres, widths = np.array([2.0, 2.0, 1.5, 2.2]), np.array([0.05, 0.08, 0.1, 0.07])
    lam0 = centres + np.array([0.09, -0.13, 0.16, 0.12])
    expected = _check_newton_against_the_numpy_loop(centres, widths, lam0)
    assert sum(e[4] for e in expected) >= 2  # halvings happened


@pytest.mark.parametrize("n", [3 * eise_newton._HALVING_BLOCK + 5, 2 * eise_newton._STEP_CHUNK_MIN + 40])
def test_newton_halves_only_the_runs_that_need_it_under_vmap(n):
    """A batch larger than a halving block: the runs whose full step overshoots are gathered and
    halved in blocks of ``_HALVING_BLOCK`` (more than one block here), the others keep their full
    step; every run's iterates are the plain loop's, alone, under vmap and in the fixed ``scan``.
    The larger batch steps in chunks of the runs still stepping (:func:`eise.newton._step_until_done`),
    and halves within them."""
    rng = np.random.default_rng(1)
    centres, widths = rng.uniform(1.5, 2.5, n), rng.uniform(0.05, 0.1, n)
    lam0 = centres + widths * rng.choice([-1.0, 1.0], n) * rng.uniform(0.5, 1.0, n)  # half overshoot at once
    expected = _check_newton_against_the_numpy_loop(centres, widths, lam0)
    halving = sum(e[4] > 0 for e in expected)
    assert eise_newton._HALVING_BLOCK < halving < n  # several blocks halve, some runs never do


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_newton_stays_where_the_relaxation_is_flat(dtype):
    """Components too far apart to merge anywhere on the grid: every grid point clusters alike, the
    relaxed EISE is constant and its slope rounding noise, so Newton stays at the grid's best and
    has converged (before, it moved λ by a noise-signed trust radius)."""
    gm = GaussianMixture.create(
        [0.5, 0.3, 0.2], [[0.0], [50.0], [100.0]], np.ones((3, 1, 1)), capacity=K, dtype=dtype
    )
    res = search_confidence(gm, ConfidenceSearch(alpha=0.01))
    assert np.all(np.asarray(res.grid_counts) == 3)  # nothing merges at any grid point
    assert float(res.lam_newton) == float(res.lam_grid) == float(res.lam)
    assert bool(res.newton_ok) and int(res.iterations) == 1
