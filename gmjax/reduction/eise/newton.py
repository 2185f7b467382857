"""Damped Newton–Raphson on the relaxed EISE: early exit per run under ``vmap`` (only the runs still
stepping step, in chunks; only rejected steps halve, in blocks), differentiated as the fixed-length scan."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from gmjax.reduction._util import first_where

_FLAT_EPS = 64  # Newton takes no step whose predicted change |f'| τ is below 64 ε |f|


def _jvp_slopes(fun, lam, args):
    """Value, first and second derivative of the scalar ``fun(λ, args)``, forward over forward
    (``λ`` is a scalar: the cheapest automatic way)."""

    def value_and_slope(x):
        return jax.jvp(lambda y: fun(y, args), (x,), (jnp.ones_like(x),))

    (f, g), (_, h) = jax.jvp(value_and_slope, (lam,), (jnp.ones_like(lam),))
    return f, g, h


def _try_scale(slopes, k, acc, lam, raw, f, args, lo, hi, start=None):
    """Backtracking's ``k``-th candidate ``λ - raw / 2^k`` (clipped to ``[lo, hi]``), evaluated with its
    slopes (the next step starts from them); ``acc = (found, (λ, f, f', f''))`` takes it if nothing was
    found yet and it does not increase ``f``. Where ``start`` (a run's first pass, :func:`_newton_step`),
    the candidate is ``λ`` itself and is taken."""
    found, best = acc
    cand = jnp.clip(lam - raw * jnp.asarray(0.5, raw.dtype) ** k, lo, hi)  # (a weak 0.5 ** int32 is float64)
    if start is not None:
        cand = jnp.where(start, lam, cand)
    at_cand = (cand, *slopes(cand, args))
    decreases = jnp.isfinite(at_cand[1]) & (at_cand[1] <= f)
    better = (~found) & (decreases if start is None else start | decreases)
    return found | better, tuple(jnp.where(better, a, b) for a, b in zip(at_cand, best))


_HALVING_BLOCK = 32  # runs per block when a batch halves only the runs whose full step was rejected


def _halvings(slopes, n_backtrack: int, k, acc, active, lam, raw, f, args, lo, hi):
    """Backtracking from candidate ``k`` on (:func:`_try_scale`) until one is taken, ``k > n_backtrack``
    or the run is not ``active``; returns ``acc``.

    Alone, a ``while_loop``. Under ``vmap`` the loop would run as long as the batch's slowest run, and
    each pass evaluates the relaxation for the whole batch; a full step is rejected in few runs (on
    the seed 000 jump system at most 0.3 % of the active runs at a step), so the batch rule gathers
    the runs still halving and runs the loop on them alone, in blocks of :data:`_HALVING_BLOCK`
    (usually one block, or none). Each run's arithmetic is the same.
    """

    def alone(k, acc, active, lam, raw, f, args, lo, hi):
        def halve(state):
            k, acc = state
            return k + 1, _try_scale(slopes, k, acc, lam, raw, f, args, lo, hi)

        keep_on = lambda s: (s[0] <= n_backtrack) & ~s[1][0] & active  # noqa: E731
        return jax.lax.while_loop(keep_on, halve, (k, acc))[1]

    batched = jax.custom_batching.custom_vmap(alone)

    @batched.def_vmap
    def _only_those_halving(axis_size, in_batched, *operands):
        spread = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + jnp.shape(a))  # noqa: E731
        operands = jax.tree_util.tree_map(spread, list(operands), list(in_batched))
        k, acc, active = operands[:3]
        out_batched = jax.tree_util.tree_map(lambda _: True, acc)
        if axis_size <= _HALVING_BLOCK:
            return jax.vmap(alone)(*operands), out_batched
        block = _HALVING_BLOCK
        n_blocks = -(-axis_size // block)
        need = (k <= n_backtrack) & ~acc[0] & active
        order = first_where(need, n_blocks * block)  # the runs still halving, then axis_size

        def one_block(state):
            j, acc = state
            rows = jax.lax.dynamic_slice(order, (j * block,), (block,))
            take = lambda a: jnp.take(a, rows, axis=0, mode="clip")  # noqa: E731
            new = jax.vmap(alone)(*jax.tree_util.tree_map(take, [k, acc, *operands[2:]]))
            return j + 1, jax.tree_util.tree_map(lambda a, b: a.at[rows].set(b, mode="drop"), acc, new)

        n_need = jnp.sum(need.astype(jnp.int32))
        _, acc = jax.lax.while_loop(lambda s: s[0] * block < n_need, one_block, (0, acc))
        return acc, out_batched

    return batched(k, acc, active, lam, raw, f, args, lo, hi)


def _newton_step(slopes, args, lo, hi, tol, radius, n_backtrack: int, early_exit: bool, carry):
    """One damped Newton step of :func:`_newton` on ``carry = (λ, f, f', f'', done, converged,
    iterations, started)``, the slopes those at ``λ``; a run already ``done`` keeps its carry.

    A run not ``started`` yet evaluates its start ``λ`` instead (the first pass of the loop): the
    start and the full steps then share one evaluation in the compiled program (each is a copy of
    the whole relaxed evaluation), and the start counts as no step."""
    lam, f, g, h, done, ok, it, started = carry
    starting = ~started
    active = ~done & started
    finite = jnp.isfinite(g) & jnp.isfinite(h)
    convex = finite & (h > 0)
    raw = jnp.where(convex, g / jnp.where(convex, h, 1.0), jnp.sign(g) * radius)
    # flat to rounding (every grid point near λ clusters alike): g is noise, so stay (and converge)
    flat = jnp.abs(g) * radius <= _FLAT_EPS * jnp.finfo(f.dtype).eps * jnp.abs(f)
    raw = jnp.where(finite & ~flat & started, jnp.clip(raw, -radius, radius), 0.0)

    # a zero step (flat) is taken at once: f re-evaluated at λ in another loop may differ in its last bit
    flat_step = active & finite & (raw == 0)
    # the full step for every run still stepping (or the start), then the halvings where it was rejected;
    # a run not stepping counts as found (it keeps its carry: see `moved`)
    take_full = (active & ~flat_step) | starting
    acc = _try_scale(slopes, 0, (~take_full, (lam, f, g, h)), lam, raw, f, args, lo, hi, start=starting)
    k = jnp.where(take_full & started, 1, n_backtrack + 1).astype(jnp.int32)
    if early_exit:  # only while some run still halves; under vmap, only those runs (_halvings)
        found, new = _halvings(slopes, n_backtrack, k, acc, active, lam, raw, f, args, lo, hi)
    else:  # every halving for every run that stepped (a run that found a candidate keeps it)
        try_scale = partial(_try_scale, slopes, lam=lam, raw=raw, f=f, args=args, lo=lo, hi=hi)
        found, new = jax.lax.fori_loop(1, n_backtrack + 1, try_scale, acc)
    found = found & (finite | starting)
    lam_new, f_new = new[:2]
    small = (jnp.abs(lam_new - lam) < tol) | (jnp.abs(f - f_new) <= tol * jnp.abs(f))
    converged = found & small
    failed = ~found
    moved = (active & found) | starting
    lam_next, f_next, g_next, h_next = (jnp.where(moved, a, b) for a, b in zip(new, (lam, f, g, h)))
    done_next = done | (active & (converged | failed))
    ok_next = jnp.where(active, converged, ok)
    return (
        lam_next,
        f_next,
        g_next,
        h_next,
        done_next,
        ok_next,
        it + active.astype(jnp.int32),
        started | starting,
    )


def _newton_loop(slopes, steps: int, n_backtrack: int, early_exit: bool, args, lam0, lo, hi, tol, radius):
    """:func:`_newton`'s iteration: a ``while_loop`` that stops once every run is done
    (``early_exit``; :func:`_step_until_done`), or a ``scan`` of ``steps + 1`` passes
    (reverse-differentiable); equal values. The first pass evaluates the start (:func:`_newton_step`)."""
    if early_exit:
        lam, f, *_, ok, it, _ = _step_until_done(slopes, steps, n_backtrack, args, lam0, lo, hi, tol, radius)
        return lam, f, ok, it
    step = partial(_newton_step, slopes, args, lo, hi, tol, radius, n_backtrack, early_exit)
    (lam, f, *_, ok, it, _), _ = jax.lax.scan(
        lambda c, _: (step(c), None), _newton_start(lam0), None, length=steps + 1
    )
    return lam, f, ok, it


def _newton_start(lam0) -> tuple:
    """The carry of :func:`_newton_step` before the first pass (``f``, ``f'``, ``f''`` unset until
    that pass evaluates the start)."""
    lam0 = jnp.asarray(lam0)
    unset = jnp.zeros_like(lam0)
    false, zero = jnp.zeros((), bool), jnp.zeros((), jnp.int32)
    return (lam0, unset, unset, unset, false, false, zero, false)


_STEP_CHUNKS = 4  # under vmap, a Newton pass steps the batch's runs still stepping in chunks of a quarter
_STEP_CHUNK_MIN = 64  # of the batch, at least this many runs (batches up to twice this step whole)


def _step_until_done(slopes, steps: int, n_backtrack: int, args, lam0, lo, hi, tol, radius) -> tuple:
    """:func:`_newton_step` from :func:`_newton_start` until the run is done or has taken ``steps``
    steps; the final carry.

    Alone, a ``while_loop``. Under ``vmap`` a ``while_loop`` runs every run in every pass until the
    batch's slowest run is done, and on the seed 000 jump system a third to a half of the runs
    stop after the first step while 13–47 % take all 8 (docs/scaling.md), so the batch rule gathers
    the runs still stepping at each pass and steps them in chunks of a quarter of the batch (at
    least :data:`_STEP_CHUNK_MIN` runs; usually as many chunks as a quarter of the runs still
    stepping, rounded up). A run's arithmetic is the same in a chunk as in the whole batch (the
    relaxed slopes sum in a fixed order from 32 runs up).
    """
    keep_on = lambda c: ~c[7] | (~c[4] & (c[6] < steps))  # noqa: E731  (not started, or still stepping)

    def step(args, lo, hi, tol, radius, carry):
        return _newton_step(slopes, args, lo, hi, tol, radius, n_backtrack, True, carry)

    def alone(args, lam0, lo, hi, tol, radius):
        return jax.lax.while_loop(keep_on, partial(step, args, lo, hi, tol, radius), _newton_start(lam0))

    batched = jax.custom_batching.custom_vmap(alone)

    @batched.def_vmap
    def _only_those_stepping(axis_size, in_batched, *operands):
        # the operands the batch shares stay shared (a constant τ stays a constant to XLA, which
        # may round its arithmetic differently from that of an array of τ's)
        axes = jax.tree_util.tree_map(lambda b: 0 if b else None, list(in_batched))
        out_batched = tuple(True for _ in range(8))
        if axis_size <= 2 * _STEP_CHUNK_MIN:
            return jax.vmap(alone, in_axes=axes)(*operands), out_batched
        args, lam0, lo, hi, tol, radius = operands
        fixed, fixed_axes = (args, lo, hi, tol, radius), (axes[0], *axes[2:])
        if axes[1] is None:
            lam0 = jnp.broadcast_to(lam0, (axis_size,) + jnp.shape(lam0))
        chunk = max(-(-axis_size // _STEP_CHUNKS), _STEP_CHUNK_MIN)
        n_chunks = -(-axis_size // chunk)

        def one_pass(carry):
            stepping = keep_on(carry)
            order = first_where(stepping, n_chunks * chunk)

            def one_chunk(state):
                j, carry = state
                rows = jax.lax.dynamic_slice(order, (j * chunk,), (chunk,))
                take = lambda axis, a: a if axis is None else jnp.take(a, rows, axis=0, mode="clip")  # noqa: E731
                gathered = jax.tree_util.tree_map(take, fixed_axes, fixed, is_leaf=lambda x: x is None)
                carry_rows = jax.tree_util.tree_map(lambda a: jnp.take(a, rows, axis=0, mode="clip"), carry)
                new = jax.vmap(step, in_axes=(*fixed_axes, 0))(*gathered, carry_rows)
                return j + 1, jax.tree_util.tree_map(lambda a, b: a.at[rows].set(b, mode="drop"), carry, new)

            n_stepping = jnp.sum(stepping.astype(jnp.int32))
            return jax.lax.while_loop(lambda s: s[0] * chunk < n_stepping, one_chunk, (0, carry))[1]

        start = jax.vmap(_newton_start)(lam0)
        return jax.lax.while_loop(lambda c: jnp.any(keep_on(c)), one_pass, start), out_batched

    return batched(args, lam0, lo, hi, tol, radius)


@partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2, 3))
def _newton_early_exit(slopes, steps: int, n_backtrack: int, differentiable, args, lam0, lo, hi, tol, radius):
    return _newton_loop(slopes, steps, n_backtrack, True, args, lam0, lo, hi, tol, radius)


@_newton_early_exit.defjvp
def _newton_early_exit_jvp(slopes, steps, n_backtrack, differentiable, primals, tangents):
    # differentiate the fixed-length scan: the same values, and reverse mode (a while_loop has none)
    (args, *rest), (args_dot, *rest_dot) = primals, tangents
    primals = (differentiable(args), *rest)
    tangents = (differentiable(args_dot), *rest_dot)
    return jax.jvp(partial(_newton_loop, slopes, steps, n_backtrack, False), primals, tangents)


def _newton(
    fun,
    args,
    lam0,
    lo,
    hi,
    steps: int,
    tol,
    radius,
    n_backtrack: int = 4,
    slopes=None,
    differentiable=lambda args: args,
):
    """Damped Newton–Raphson on the scalar function ``fun(λ, args)`` over ``[lo, hi]``.

    Each step is the Newton step ``g / h`` (or, where the curvature is not positive, a descent step
    of length ``radius``), clipped to the trust radius ``radius`` and halved up to ``n_backtrack``
    times until the function decreases. Where ``|g| radius <= 64 ε |f|`` the function is flat to
    rounding (for the relaxed EISE: every grid point near ``λ`` clusters alike) and ``g`` is noise:
    no step is taken and Newton has converged where it is. It stops when ``|Δλ| < tol`` or the relative change of the
    function is below ``tol`` (seed 000 Fig. 2: "the change of the adjacent EISE is less than a
    small value") — *converged* — or when no halving decreases the function or a derivative is not
    finite — *failed* — or after ``steps`` steps.

    Every candidate is evaluated with its derivatives (``slopes``), so the step after an accepted
    candidate starts from them: one evaluation per step where the full step decreases the
    function (nearly always; the halvings are rare), instead of the derivatives at ``λ`` and the
    value at the candidate apart. The start is evaluated by the loop's first pass, so the compiled
    program holds two copies of the evaluation (the step loop's and the halving blocks'), not three.

    The loops exit early: the step loop once the run is done, the halvings once a candidate
    decreases ``fun``. Under ``vmap`` each pass of the step loop steps only the runs still stepping,
    gathered into chunks of a quarter of the batch (:func:`_step_until_done`), until every run is
    done, and only the runs whose full step was rejected halve, gathered into blocks
    (:func:`_halvings`). ``while_loop`` has no reverse mode, so a custom JVP differentiates the
    equivalent fixed-length ``scan`` instead: the values are identical (bitwise in
    ``tests/reduction/eise/test_newton.py``; compiled inside the whole search, XLA may fuse the two differently, and
    on 4 × 1000 jump-system searches 0–4 runs' ``λ`` differed by up to 1e-14 relative) and the
    derivatives are those of the ``scan`` (``jax.grad`` works).
    ``fun`` must take everything it differentiates through ``args`` (a pytree), not a closure.
    ``slopes(λ, args) -> (f, f', f'')`` gives the value and derivatives (default:
    forward-over-forward ``jvp`` of ``fun``).
    ``differentiable(args)``: the ``args`` (and their tangents) the differentiated ``scan`` takes,
    the same arithmetic (:func:`search_confidence` drops :class:`_Pairs`, whose loop has no reverse
    mode: the scan's values then equal the loop's to rounding).

    Returns:
        ``(λ, fun(λ), converged, iterations)``.
    """
    slopes = partial(_jvp_slopes, fun) if slopes is None else slopes
    return _newton_early_exit(slopes, steps, n_backtrack, differentiable, args, lam0, lo, hi, tol, radius)
