"""Private helpers shared by the reducers: finalisation into the output capacity, identity labels.

Validation lives in :mod:`gmjax._validate`, the small-matrix algebra in :mod:`gmjax.gaussian` (``spd_*``).
"""

from __future__ import annotations

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
    _, order_top = jax.lax.top_k(jnp.where(work.mask, work.weights, -jnp.inf), capacity)
    idx = jnp.where(overflow, order_top, order_keep)
    out = jax.tree_util.tree_map(lambda a: a[idx], work)
    valid = work.mask[idx]
    out = mixture.sanitize(out._replace(mask=valid))
    pos = jnp.full(Kw, -1, jnp.int32).at[idx].max(
        jnp.where(valid, jnp.arange(capacity, dtype=jnp.int32), -1)
    )
    labels_out = jnp.where(labels >= 0, pos[jnp.maximum(labels, 0)], -1)
    kept = jnp.zeros(Kw, bool).at[idx].set(valid)
    dropped = jnp.sum(jnp.where(work.mask & ~kept, work.weights, 0.0))
    return out, labels_out, overflow, dropped


def identity_labels(gm: GaussianMixture) -> jax.Array:
    """``(K,)`` labels mapping every live slot to itself and padded slots to ``-1``."""
    return jnp.where(gm.mask, jnp.arange(gm.capacity, dtype=jnp.int32), -1)
