"""West's reduction (West 1993) and its enhanced variant (Chen, Chang & Smith 2010), over the greedy
engine in :mod:`gmjax.reduction._greedy`."""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction._greedy import finish, greedy_steps, init_state
from gmjax.reduction.base import ReductionInfo, Stateless, calls

__all__ = ["west", "west_distance", "West"]


def west_distance(mi: Array, Pi: Array, mj: Array, Pj: Array, metric: str) -> Array:
    """West's nearness of component ``j`` to the selected component ``i``.

    ``"kl"``: ``KL(N_i || N_j)``; ``"ise"``: ``ISE(N_i, N_j) = J_ii + J_jj - 2 J_ij`` of the
    unit-weight Gaussians (the ISE-cost variant).
    """
    if metric == "kl":
        return gaussian.spd_kl(mi, Pi, mj, Pj)
    jij = jnp.exp(gaussian.spd_logpdf(mi, mj, Pi + Pj))
    jii = jnp.exp(gaussian.spd_logpdf(mi, mi, 2.0 * Pi))
    jjj = jnp.exp(gaussian.spd_logpdf(mj, mj, 2.0 * Pj))
    return jii + jjj - 2.0 * jij


@partial(jax.jit, static_argnames=("num_out", "capacity", "metric", "enhanced"))
def _west(gm, num_out, threshold, capacity, metric, enhanced):
    K = gm.capacity

    def select(s):
        # West (1993) Sec. 2.3: the smallest weight; the "enhanced" variant (Chen, Chang & Smith
        # 2010, Sec. 3.2) ranks by w / det P instead.
        score = s.w / jnp.exp(s.logdet) if enhanced else s.w
        i = jnp.argmin(jnp.where(s.mask, score, jnp.inf)).astype(jnp.int32)
        if metric == "kl":  # KL(N_i || N_k) from the carried P_k^{-1} and log det P_k
            dist = gaussian.spd_kl_from_inverse(s.m[i], s.P[i], s.logdet[i], s.m, s.Pinv, s.logdet)
        else:
            dist = west_distance(s.m[i], s.P[i], s.m, s.P, metric)
        dist = jnp.where(s.mask & (jnp.arange(K) != i), dist, jnp.inf)
        j = jnp.argmin(dist).astype(jnp.int32)
        return i, j, dist[j]

    kl = metric == "kl"
    ld = gaussian.spd_logdet(gm.covs) if kl or enhanced else None
    Pinv = gaussian.spd_inv(gm.covs) if kl else None
    body, n_steps = greedy_steps(gm, num_out, threshold, select, None)
    s = jax.lax.fori_loop(0, n_steps, body, init_state(gm, jnp.zeros((1, 1), gm.weights.dtype), ld, Pinv))
    return finish(gm, s, n_steps, capacity)


def west(
    gm: GaussianMixture,
    num_out: int,
    threshold: Any = None,
    *,
    metric: str = "kl",
    enhanced: bool = False,
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """West's reduction (West 1993, JRSS-B 55(2), Sec. 2.3): merge the smallest-weight component
    with its nearest neighbour, repeatedly.

    "Nearest" is ``KL(N_i || N_j)`` (``metric="kl"``) or the ISE between the two unit-weight
    Gaussians (``metric="ise"``, the ISE-cost variant), following the Tracker Component Library's
    ``WestGaussReduction``. ``enhanced=True`` selects by ``w / det P`` (the enhanced West of Chen,
    Chang & Smith 2010). Merging stops at ``num_out`` components or when the nearest distance exceeds
    ``threshold``. Other arguments as in :func:`runnalls`.
    """
    del key
    if metric not in ("kl", "ise"):
        raise ValueError(f"metric: expected 'kl' or 'ise', got {metric!r}")
    return _util.reduce_count_threshold(
        _west, gm, num_out, threshold, capacity, metric=metric, enhanced=bool(enhanced)
    )


@pytree_dataclass
class West(Stateless):
    """Reducer config for :func:`west` (``threshold`` dynamic)."""

    num_out: int = static_field(10)
    threshold: Any = float("inf")
    metric: str = static_field("kl")
    enhanced: bool = static_field(False)
    capacity: int | None = static_field(None)

    __call__ = calls(west)
