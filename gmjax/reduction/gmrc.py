"""GMRC: Gaussian mixture reduction via clustering (Schieferdecker & Huber 2009)."""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from gmjax import _validate, gaussian
from gmjax._pytree import pytree_dataclass, static_field
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction.base import ReductionInfo, Stateless, calls
from gmjax.reduction.merge import merge_labels
from gmjax.reduction.runnalls import _runnalls

__all__ = ["gmrc", "GMRC", "kl_upper_bound"]


def kl_upper_bound(gm: GaussianMixture, centers: GaussianMixture, labels: jax.Array) -> jax.Array:
    """``sum_i w_i KL(N_i || N_{c(i)})`` — the convexity bound on ``KL(f || g)`` that GMRC's
    k-means iterations decrease (Schieferdecker & Huber 2009, Sec. III)."""
    lab = jnp.maximum(labels, 0)
    kl = gaussian.spd_kl(gm.means, gm.covs, centers.means[lab], centers.covs[lab])
    return jnp.sum(jnp.where(gm.mask & (labels >= 0), gm.weights * kl, 0.0))


class _S(NamedTuple):
    centers: GaussianMixture
    labels: jax.Array
    it: jax.Array
    done: jax.Array


@partial(jax.jit, static_argnames=("num_out", "max_iter", "capacity"))
def _gmrc(gm, num_out, max_iter, capacity):
    init, info0 = _runnalls(gm, num_out, jnp.asarray(jnp.inf, gm.weights.dtype), num_out)

    def assign(c):
        kl = gaussian.spd_kl(gm.means[:, None], gm.covs[:, None], c.means[None], c.covs[None])  # (K, num_out)
        kl = jnp.where(c.mask[None, :], kl, jnp.inf)
        return jnp.where(gm.mask, jnp.argmin(kl, axis=1).astype(jnp.int32), -1)

    def cond(s):
        return (~s.done) & (s.it < max_iter)

    def body(s):
        labels = assign(s.centers)
        new = merge_labels(gm, labels, num_out, "moment")
        # an emptied cluster keeps its previous center for the next assignment (and its weight is 0)
        keep = new.mask
        centers = GaussianMixture(
            jnp.where(keep, new.weights, 0.0),
            jnp.where(keep[:, None], new.means, s.centers.means),
            jnp.where(keep[:, None, None], new.covs, s.centers.covs),
            s.centers.mask,
        )
        return _S(centers, labels, s.it + 1, jnp.all(labels == s.labels))

    s0 = _S(
        init, jnp.where(info0.labels >= 0, info0.labels, -1), jnp.zeros((), jnp.int32), jnp.asarray(False)
    )
    s = jax.lax.while_loop(cond, body, s0)
    merged = merge_labels(gm, s.labels, num_out, "moment")
    cost = kl_upper_bound(gm, merged, s.labels)
    aux = {"iterations": s.it, "converged": s.done}
    return _util.finalize_info(gm, merged, s.labels, capacity, cost=cost, aux=aux)


def gmrc(
    gm: GaussianMixture,
    num_out: int,
    *,
    max_iter: int = 50,
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """GMRC (Schieferdecker & Huber 2009, "Gaussian mixture reduction via clustering", FUSION).

    Initialise ``num_out`` clusters with Runnalls' greedy reduction, then iterate k-means: assign
    every original component to the center ``c`` minimising ``KL(N_i || N_c)`` and replace every
    center by the moment-preserving merge of its members (which minimises the bound
    ``sum_i w_i KL(N_i || N_c(i))``, :func:`kl_upper_bound`, reported as ``info.cost``). Stops when
    the assignment no longer changes or after ``max_iter`` iterations (static; ``while_loop``).

    Args:
        gm: input mixture, capacity ``K``.
        num_out: static target count.
        max_iter: static bound on the k-means iterations.
        capacity: static output capacity (default ``K``).
        key: unused.
    """
    del key
    _validate.validate_mixture(gm)
    num_out = _validate.validate_count(num_out, "num_out", 1, gm.capacity)
    cap = _validate.validate_capacity(capacity, gm, minimum=num_out)
    max_iter = _validate.validate_count(max_iter, "max_iter", 0, 2**31 - 1)
    return _gmrc(gm, num_out, max_iter, cap)


@pytree_dataclass
class GMRC(Stateless):
    """Reducer config for :func:`gmrc`."""

    num_out: int = static_field(10)
    max_iter: int = static_field(50)
    capacity: int | None = static_field(None)

    __call__ = calls(gmrc)
