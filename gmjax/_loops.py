"""A loop that exits early but differentiates as its fixed-length twin.

:func:`bounded_loop` runs ``carry, go = body(carry)`` at most ``n`` times in a ``while_loop`` (fast:
splits and merges are rare) and gets its derivatives, forward and reverse, from a custom JVP over the
same body run ``n`` times in a ``fori_loop`` (identical values). Used by the seed 001 filter's split
stage and its Step 6 merge (:mod:`gmjax.reduction.step6`).
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

__all__ = ["bounded_loop"]


def _fixed_loop(n: int, body: Callable, carry: Any) -> Any:
    """``n`` trips of ``body`` (a ``fori_loop`` with a static trip count); after the first
    ``go = False`` the trips are no-ops."""

    def fbody(_, c):
        carry, go = c
        new, did = body(carry)
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(go, a, b), new, carry)
        return new, go & did

    return jax.lax.fori_loop(0, n, fbody, (carry, jnp.asarray(True)))[0]


def _while_loop(n: int, body: Callable, carry: Any) -> Any:
    """At most ``n`` trips of ``body``, exiting after the first ``go = False`` (a ``while_loop``)."""

    def cond(c):
        i, _, go = c
        return (i < n) & go

    def wbody(c):
        i, carry, _ = c
        new, did = body(carry)
        return i + 1, new, did

    return jax.lax.while_loop(cond, wbody, (jnp.zeros((), jnp.int32), carry, jnp.asarray(True)))[1]


def _hoist(body: Callable, carry: Any) -> tuple[Callable, list]:
    """``body`` as ``fn(carry, *consts)`` with every closed-over value (floats, ints, bools) explicit.

    ``jax.closure_convert`` hoists only floating-point values; a custom-JVP function must not close
    over any tracer, so the body is traced once to a jaxpr and its constants are passed explicitly.
    """
    closed, out_shape = jax.make_jaxpr(body, return_shape=True)(carry)
    out_tree = jax.tree_util.tree_structure(out_shape)

    def fn(c, *consts):
        out = jax.core.eval_jaxpr(closed.jaxpr, consts, *jax.tree_util.tree_leaves(c))
        return jax.tree_util.tree_unflatten(out_tree, out)

    return fn, closed.consts


def bounded_loop(n: int, body: Callable, carry: Any) -> Any:
    """Run ``carry, go = body(carry)`` at most ``n`` times, stopping after the first ``go = False``.

    The value is a ``while_loop`` that exits early (splits and merges are rare, so this is much
    faster than a fixed trip count, under ``vmap`` too). Its derivatives (forward and reverse mode)
    come from a custom JVP rule that differentiates the same loop run with the static trip count
    ``n`` (:func:`_fixed_loop`, identical values), so ``jax.grad`` works and costs the fixed loop
    only when differentiating. Every traced value closed over by ``body`` (thresholds, noises, the
    time) is hoisted into an explicit argument (:func:`_hoist`), so no tangent is lost and no
    tracer leaks out of the rule.
    """
    if n <= 0:
        return carry
    fn, consts = _hoist(body, carry)

    @jax.custom_jvp
    def loop(carry, *consts):
        return _while_loop(n, lambda c: fn(c, *consts), carry)

    @loop.defjvp
    def loop_jvp(primals, tangents):
        return jax.jvp(lambda c, *k: _fixed_loop(n, lambda x: fn(x, *k), c), primals, tangents)

    return loop(carry, *consts)
