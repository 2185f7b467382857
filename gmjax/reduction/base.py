"""The Reducer protocol and the information every reducer returns (docs/design.md §3)."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple, Protocol

import jax.numpy as jnp

from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array, PRNGKey
from gmjax.mixture import GaussianMixture

__all__ = ["ReductionInfo", "Reducer", "EmptyState", "Stateless", "CountThreshold", "calls", "make_info"]


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
        invalid_threshold: ``()`` bool, True when a dynamic (traced) threshold or parameter of the
            reducer was NaN. The reducer then returns its input unchanged (fitted to the output
            capacity, the heaviest kept with ``overflow`` if it does not fit), ``cost = 0``, and
            ``aux`` is not meaningful. Every reducer fills it (``False`` by default in
            :func:`make_info`); concrete NaN thresholds are refused eagerly with ``ValueError``.
    """

    n_in: Array
    n_out: Array
    pruned_mass: Array
    labels: Array
    overflow: Array
    cost: Array
    aux: dict[str, Any]
    invalid_threshold: Array = False  # type: ignore[assignment]  # a bool default, an array once made


def make_info(
    gm_in: GaussianMixture,
    gm_out: GaussianMixture,
    labels: Array,
    *,
    pruned_mass: Array | float = 0.0,
    overflow: Array | bool = False,
    cost: Array | float = 0.0,
    aux: dict[str, Any] | None = None,
    invalid_threshold: Array | bool = False,
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
        invalid_threshold=jnp.asarray(invalid_threshold, bool),
    )


class EmptyState(NamedTuple):
    """The state of a stateless reducer (no leaves), as optax's ``EmptyState``."""


class Reducer(Protocol):
    """The one reducer contract: a frozen pytree config that *is* the algorithm.

    * ``init(capacity) -> state``: a fresh state for mixtures of ``capacity`` slots
      (:class:`EmptyState` for stateless reducers);
    * ``reduce(gm, state, *, key=None) -> (gm, state, ReductionInfo)``.

    Static fields are sizes and iteration counts; the other fields (thresholds) are pytree leaves,
    so ``jax.grad`` and optax reach them and changing them does not recompile. Every leaf of a
    reducer state has a leading slot axis aligned with the mixture it describes: a filter that
    expands each component into ``n`` children repeats each slot's entries ``n`` times
    (``jnp.repeat(leaf, n, axis=0)``) before the next call, and a stateful reducer returns exactly
    its configured ``capacity`` slots. ``reducer(gm, *, key=None) -> (gm, ReductionInfo)`` is the
    same reduction from a fresh state.
    """

    def init(self, capacity: int) -> Any: ...

    def reduce(
        self, gm: GaussianMixture, state: Any, *, key: PRNGKey | None = None
    ) -> tuple[GaussianMixture, Any, ReductionInfo]: ...

    def __call__(
        self, gm: GaussianMixture, *, key: PRNGKey | None = None
    ) -> tuple[GaussianMixture, ReductionInfo]: ...


def calls(fn: Callable[..., tuple[GaussianMixture, ReductionInfo]]) -> Callable:
    """The ``__call__`` of a stateless reducer config that calls the reducer function ``fn`` with every
    field of the config by name: ``fn(gm, **fields, key=key)`` (the function and its config share
    their argument names; as optax's ``stateless`` makes a transformation of a function)::

        @pytree_dataclass
        class West(Stateless):
            num_out: int = static_field(3)
            ...
            __call__ = calls(west)
    """

    def __call__(
        self, gm: GaussianMixture, *, key: PRNGKey | None = None
    ) -> tuple[GaussianMixture, ReductionInfo]:
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return fn(gm, **fields, key=key)

    __call__.__doc__ = f"``{fn.__name__}(gm, **fields, key=key)``: ``(reduced, info)``."
    return __call__


def reduces_with_state(fn: Callable[..., tuple[GaussianMixture, Any, ReductionInfo]]) -> Callable:
    """The ``reduce`` of a stateful reducer config that calls the reducer function ``fn`` with the
    carried state and every field of the config by name: ``fn(gm, state, **fields, key=key)``
    (the stateful counterpart of :func:`calls`)."""

    def reduce(
        self, gm: GaussianMixture, state: Any, *, key: PRNGKey | None = None
    ) -> tuple[GaussianMixture, Any, ReductionInfo]:
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return fn(gm, state, **fields, key=key)

    reduce.__doc__ = f"``{fn.__name__}(gm, state, **fields, key=key)``: ``(reduced, new_state, info)``."
    return reduce


class Stateless:
    """Mixin giving a stateless reducer config (one that defines ``__call__``, e.g. by
    :func:`calls`) the protocol."""

    def init(self, capacity: int) -> EmptyState:
        """The (empty) state; ``capacity`` is unused."""
        del capacity
        return EmptyState()

    def reduce(
        self, gm: GaussianMixture, state: Any, *, key: PRNGKey | None = None
    ) -> tuple[GaussianMixture, Any, ReductionInfo]:
        """``(reduced, state, info)``; the state passes through unchanged."""
        out, info = self(gm, key=key)  # type: ignore[operator]
        return out, state, info


@pytree_dataclass
class CountThreshold(Stateless):
    """The fields of a greedy reducer config that merges down to ``num_out`` components or until the
    cheapest merge costs more than ``threshold`` (:class:`~gmjax.reduction.Runnalls`,
    :class:`~gmjax.reduction.Salmond`, :class:`~gmjax.reduction.COWA`); a subclass adds its
    ``__call__ = calls(fn)``.

    Attributes:
        num_out: static target count.
        threshold: the cost bound (traced; default ``inf``, count only).
        capacity: static output capacity (default the input's).
    """

    num_out: int = static_field(10)
    threshold: Any = float("inf")
    capacity: int | None = static_field(None)
