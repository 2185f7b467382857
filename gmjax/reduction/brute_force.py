"""Brute-force ISE-optimal merging over every partition (the small-``K`` test oracle)."""

from __future__ import annotations

from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import _validate
from gmjax._pytree import pytree_dataclass, static_field
from gmjax.metrics import ise
from gmjax.mixture import GaussianMixture, compact
from gmjax.reduction import _util
from gmjax.reduction.base import ReductionInfo, Stateless, calls
from gmjax.reduction.merge import merge_labels

__all__ = ["brute_force", "BruteForce", "set_partitions", "MAX_PARTITIONS"]

MAX_PARTITIONS = 2_000_000


def _count_partitions(n: int, k: int) -> int:
    # sum of Stirling numbers of the second kind S(n, b), b = 1..k
    S = [[0] * (k + 1) for _ in range(n + 1)]
    S[0][0] = 1
    for i in range(1, n + 1):
        for b in range(1, k + 1):
            S[i][b] = b * S[i - 1][b] + S[i - 1][b - 1]
    return sum(S[n][1:])


@lru_cache(maxsize=32)
def set_partitions(n: int, k: int) -> np.ndarray:
    """All partitions of ``n`` slots into at most ``k`` blocks as restricted growth strings
    ``(num_partitions, n)`` int32 (block of slot ``i`` is ``<= 1 + max`` of the earlier blocks)."""
    out = []

    def rec(prefix, maxb):
        if len(prefix) == n:
            out.append(list(prefix))
            return
        for b in range(min(maxb + 2, k)):
            prefix.append(b)
            rec(prefix, max(maxb, b))
            prefix.pop()

    rec([], -1)
    return np.asarray(out, np.int32).reshape(-1, n)


@partial(jax.jit, static_argnames=("num_out", "capacity", "batch_size"))
def _brute(gm, num_out, capacity, batch_size):
    gmc = compact(gm)  # live slots first: partitions differing only on padding coincide
    parts = jnp.asarray(set_partitions(gm.capacity, num_out))
    # score on normalised weights: moment merges are linear in the weights, so the ISE of every
    # partition scales by total^2 and the argmin is unchanged, but tiny weights (~1e-300) no longer
    # underflow every ISE to 0 (which made every partition "optimal")
    total = jnp.sum(jnp.where(gmc.mask, gmc.weights, 0.0))
    scale = jnp.where(total > 0, total, 1.0)
    gmn = gmc._replace(weights=gmc.weights / scale)

    def score(lab):
        lab = jnp.where(gmn.mask, lab, -1)
        red = merge_labels(gmn, lab, num_out, "moment")
        return ise(gmn, red)

    vals = jax.lax.map(score, parts, batch_size=batch_size)
    best = jnp.argmin(vals)
    lab = jnp.where(gmc.mask, parts[best], -1)
    red = merge_labels(gmc, lab, num_out, "moment")
    # labels of the original slots: gmc slot r came from gm slot order[r]
    order, _ = _util.live_first(gm.mask)
    labels_in = jnp.zeros(gm.capacity, jnp.int32).at[order].set(lab)
    cost = vals[best] * scale * scale  # the ISE of the weights as given (may underflow to 0)
    return _util.finalize_info(gm, red, labels_in, capacity, cost=cost)


def brute_force(
    gm: GaussianMixture,
    num_out: int,
    *,
    capacity: int | None = None,
    batch_size: int = 1024,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """The ISE-optimal reduction among all moment-preserving merges of a partition of the live
    components into at most ``num_out`` clusters (exhaustive; for small ``K`` only).

    This is the test oracle: any reducer that outputs a moment-preserving merge of a partition
    (Runnalls, West, Salmond, k-means, GMRC) has ISE ``>=`` this one. Reducers that also prune or
    re-weight (Williams, COWA, ``ise_refine``) are outside that class and can be lower.

    Args:
        gm: input mixture; its capacity ``K`` fixes the enumeration (Bell-type growth:
            ``K = 10, num_out = 5`` is 86,472 partitions; more than ``MAX_PARTITIONS`` raises).
        num_out: static, ``1 <= num_out <= K``.
        capacity: static output capacity (default ``K``).
        batch_size: partitions evaluated per vectorised batch.
        key: unused.

    Returns:
        ``(reduced mixture, info)``; ``info.cost`` is the optimal ISE.
    """
    del key
    _validate.validate_mixture(gm)
    num_out = _validate.validate_count(num_out, "num_out", 1, gm.capacity)
    cap = _validate.validate_capacity(capacity, gm, minimum=num_out)
    count = _count_partitions(gm.capacity, num_out)
    if count > MAX_PARTITIONS:
        raise ValueError(
            f"gm: capacity {gm.capacity} with num_out {num_out} has {count} partitions "
            f"(> {MAX_PARTITIONS}); brute_force is for small mixtures"
        )
    return _brute(gm, num_out, cap, int(batch_size))


@pytree_dataclass
class BruteForce(Stateless):
    """Reducer config for :func:`brute_force`."""

    num_out: int = static_field(3)
    capacity: int | None = static_field(None)

    __call__ = calls(brute_force)
