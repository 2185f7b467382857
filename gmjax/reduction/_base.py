"""The Reducer protocol and the information every reducer returns (DESIGN §3)."""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol

import jax.numpy as jnp

from gmjax._types import Array, PRNGKey
from gmjax.mixture import GaussianMixture

__all__ = ["ReductionInfo", "Reducer", "make_info"]


class ReductionInfo(NamedTuple):
    """What a reduction did (a pytree; batch with vmap).

    Attributes:
        n_in: ``()`` int32, live components before.
        n_out: ``()`` int32, live components after.
        pruned_mass: ``()`` total weight removed by pruning (before any renormalisation).
        labels: ``(K_in,)`` int32, output slot of each input slot; ``-1`` for pruned or padded slots.
        overflow: ``()`` bool, True when more components survived than the output capacity holds
            (the heaviest were kept).
        cost: ``()`` the reducer's own cost of the result (ISE, EISE, summed KL bound, ...), or 0.
        aux: reducer-specific extras (e.g. PCM's searched ``lambda``), a dict of arrays.
    """

    n_in: Array
    n_out: Array
    pruned_mass: Array
    labels: Array
    overflow: Array
    cost: Array
    aux: dict[str, Any]


def make_info(
    gm_in: GaussianMixture,
    gm_out: GaussianMixture,
    labels: Array,
    *,
    pruned_mass: Array | float = 0.0,
    overflow: Array | bool = False,
    cost: Array | float = 0.0,
    aux: dict[str, Any] | None = None,
) -> ReductionInfo:
    """Assemble a :class:`ReductionInfo` with the standard dtypes."""
    dtype = gm_in.weights.dtype
    return ReductionInfo(
        n_in=jnp.sum(gm_in.mask.astype(jnp.int32)),
        n_out=jnp.sum(gm_out.mask.astype(jnp.int32)),
        pruned_mass=jnp.asarray(pruned_mass, dtype),
        labels=jnp.asarray(labels, jnp.int32),
        overflow=jnp.asarray(overflow, bool),
        cost=jnp.asarray(cost, dtype),
        aux={} if aux is None else aux,
    )


class Reducer(Protocol):
    """A configured reduction: ``reducer(gm, *, key=None) -> (GaussianMixture, ReductionInfo)``.

    Implementations are frozen :func:`gmjax._pytree.pytree_dataclass` configs whose static fields
    are sizes / iteration counts and whose dynamic fields are thresholds.
    """

    def __call__(
        self, gm: GaussianMixture, *, key: PRNGKey | None = None
    ) -> tuple[GaussianMixture, ReductionInfo]: ...
