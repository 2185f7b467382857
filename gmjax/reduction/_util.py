"""Private helpers shared by the reducers: finalisation into the output capacity, identity labels.

Validation lives in :mod:`gmjax._validate`, the small-matrix algebra in :mod:`gmjax.gaussian` (``spd_*``).
"""

from __future__ import annotations

import functools
import inspect
from typing import Any, Callable

import jax
import jax.numpy as jnp

from gmjax import mixture
from gmjax.mixture import GaussianMixture

# ----------------------------------------------------------------------------- finalisation


def finalize(
    gm_in: GaussianMixture,
    work: GaussianMixture,
    labels: jax.Array,
    capacity: int,
):
    """Compact a working mixture (capacity ``K_w``) into ``capacity`` output slots.

    Live slots keep their relative order; if more than ``capacity`` are live, the heaviest are kept
    (``overflow``) and their weights are *not* renormalised (the dropped weight is ``dropped``).

    Args:
        gm_in: the reducer's input (only used for shapes).
        work: the working mixture; its ``mask`` says which slots are live.
        labels: ``(K_in,)`` working slot of every input slot, ``-1`` for none.
        capacity: static output capacity.

    Returns:
        ``(gm_out, labels_out, overflow, dropped_mass)``.
    """
    del gm_in
    Kw = work.capacity
    n_live = jnp.sum(work.mask.astype(jnp.int32))
    overflow = n_live > capacity
    if capacity >= Kw:
        out = mixture.pad(work, capacity) if capacity > Kw else work
        order = jnp.argsort(~out.mask, stable=True)
        out = jax.tree_util.tree_map(lambda a: a[order], out)
        pos = jnp.zeros(capacity, jnp.int32).at[order].set(jnp.arange(capacity, dtype=jnp.int32))
        labels_out = jnp.where(labels >= 0, pos[jnp.maximum(labels, 0)], -1)
        return mixture.sanitize(out), labels_out, jnp.asarray(False), jnp.zeros((), work.weights.dtype)
    order_keep = jnp.argsort(~work.mask, stable=True)[:capacity]
    order_top, _ = mixture.heaviest_slots(work.weights, work.mask, capacity)
    idx = jnp.where(overflow, order_top, order_keep)
    out = jax.tree_util.tree_map(lambda a: a[idx], work)
    valid = work.mask[idx]
    out = mixture.sanitize(out._replace(mask=valid))
    pos = jnp.full(Kw, -1, jnp.int32).at[idx].max(jnp.where(valid, jnp.arange(capacity, dtype=jnp.int32), -1))
    labels_out = jnp.where(labels >= 0, pos[jnp.maximum(labels, 0)], -1)
    kept = jnp.zeros(Kw, bool).at[idx].set(valid)
    dropped = jnp.sum(jnp.where(work.mask & ~kept, work.weights, 0.0))
    return out, labels_out, overflow, dropped


def identity_labels(gm: GaussianMixture) -> jax.Array:
    """``(K,)`` labels mapping every live slot to itself and padded slots to ``-1``."""
    return jnp.where(gm.mask, jnp.arange(gm.capacity, dtype=jnp.int32), -1)


# ----------------------------------------------------------------------------- NaN thresholds


def _traced_float(x: Any) -> bool:
    return isinstance(x, jax.core.Tracer) and jnp.issubdtype(x.dtype, jnp.inexact)


def unchanged(gm: GaussianMixture, capacity: int):
    """The "no reduction" result: ``gm`` fitted to ``capacity`` slots by :func:`finalize`.

    Returns:
        ``(gm_out, labels, overflow, dropped_mass)``.
    """
    return finalize(gm, gm, identity_labels(gm), capacity)


def select_unchanged(bad: jax.Array, gm: GaussianMixture, out: GaussianMixture, info: Any):
    """``(out, info)`` where ``bad`` is False; else the input unchanged (see :func:`unchanged`)
    with ``cost = 0``; ``info.invalid_threshold = bad`` either way."""
    same, labels, overflow, dropped = unchanged(gm, out.capacity)
    pick = functools.partial(jnp.where, bad)
    out = jax.tree_util.tree_map(pick, same, out)
    info = info._replace(
        n_out=pick(jnp.sum(same.mask.astype(jnp.int32)), info.n_out),
        pruned_mass=pick(dropped.astype(info.pruned_mass.dtype), info.pruned_mass),
        labels=pick(labels, info.labels),
        overflow=pick(overflow, info.overflow),
        cost=pick(jnp.zeros_like(info.cost), info.cost),
        invalid_threshold=jnp.asarray(bad, bool) | jnp.asarray(info.invalid_threshold, bool),
    )
    return out, info


def guard_nan(**safe: Any) -> Callable:
    """Decorate a public reducer ``f(gm, ...) -> (out, info)`` (or ``(out, state, info)``) so a
    *traced* NaN in any of the named arguments gives a defined, flagged result.

    ``safe`` maps argument names to a valid stand-in. When any traced floating leaf of those
    arguments is NaN, the reducer runs on the stand-ins (so no NaN reaches its arithmetic or its
    gradients) and its result is replaced by the input unchanged (:func:`select_unchanged`), with
    ``info.invalid_threshold`` set; a stateful reducer's new state is then a fresh one
    (``state_init(capacity)``, passed as ``safe["state_init"]``). Concrete NaNs are left to the
    reducer's eager validation (a ``ValueError``).
    """
    state_init = safe.pop("state_init", None)

    def deco(fn: Callable) -> Callable:
        sig = inspect.signature(fn)
        first = next(iter(sig.parameters))

        @functools.wraps(fn)
        def wrapped(*args, **kwargs):
            bound = sig.bind(*args, **kwargs)
            bound.apply_defaults()
            bad = None
            for name, stand_in in safe.items():
                value = bound.arguments.get(name)
                leaves = jax.tree_util.tree_leaves(value)
                if not any(_traced_float(x) for x in leaves):
                    continue

                def clean(x, stand_in=stand_in):
                    nonlocal bad
                    if not _traced_float(x):
                        return x
                    nan = jnp.any(jnp.isnan(x))
                    bad = nan if bad is None else bad | nan
                    return jnp.where(jnp.isnan(x), jnp.asarray(stand_in, x.dtype), x)

                bound.arguments[name] = jax.tree_util.tree_map(clean, value)
            result = fn(*bound.args, **bound.kwargs)
            if bad is None:
                return result
            gm = bound.arguments[first]
            if len(result) == 3:
                out, state, info = result
                out, info = select_unchanged(bad, gm, out, info)
                fresh = state_init(out.capacity)
                state = jax.tree_util.tree_map(functools.partial(jnp.where, bad), fresh, state)
                return out, state, info
            return select_unchanged(bad, gm, *result)

        return wrapped

    return deco
