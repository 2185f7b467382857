"""Frozen dataclasses that are JAX pytrees, with static (hashable, compile-time) fields.

Configs of reducers and filters use them: sizes and iteration counts are ``static_field()`` (part of
the tree structure, so changing them recompiles), thresholds are ordinary fields (leaves, so
``jax.grad`` and optax reach them and changing them does not recompile).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, TypeVar, cast

import jax

if TYPE_CHECKING:  # typing.dataclass_transform is Python 3.11+; type checkers know typing_extensions
    from typing_extensions import dataclass_transform
else:

    def dataclass_transform(**kwargs):
        return lambda decorator: decorator


__all__ = ["pytree_dataclass", "static_field"]

T = TypeVar("T")


def static_field(default: Any = dataclasses.MISSING, **kwargs: Any) -> Any:
    """A dataclass field that is static auxiliary data of the pytree (not a leaf)."""
    metadata = dict(kwargs.pop("metadata", {}) or {}, static=True)
    return dataclasses.field(default=default, metadata=metadata, **kwargs)


@dataclass_transform(frozen_default=True)  # static_field(v) reads as an ordinary default v
def pytree_dataclass(cls: type[T]) -> type[T]:
    """Decorate ``cls`` as a frozen dataclass registered as a pytree.

    Fields declared with :func:`static_field` go into the tree definition; the rest are children.
    The tree definition carries the class itself beside the static values: two configs of different
    classes with equal static fields (``PruneTop(num_out=3)``, ``BruteForce(num_out=3)``) must never
    compare equal as tree structures, or a ``jit`` cache could serve one the other's compiled code
    (``register_dataclass`` compares only the static values).
    """
    cls = dataclasses.dataclass(frozen=True)(cls)
    fields = dataclasses.fields(cast(Any, cls))  # a dataclass from the line above
    data_names = tuple(f.name for f in fields if not f.metadata.get("static", False))
    meta_names = tuple(f.name for f in fields if f.metadata.get("static", False))

    def flatten(obj):
        children = [(jax.tree_util.GetAttrKey(n), getattr(obj, n)) for n in data_names]
        return children, (cls, tuple(getattr(obj, n) for n in meta_names))

    def unflatten(aux, children):
        obj = object.__new__(cls)
        for name, value in zip(meta_names, aux[1]):
            object.__setattr__(obj, name, value)
        for name, value in zip(data_names, children):
            object.__setattr__(obj, name, value)
        return obj

    jax.tree_util.register_pytree_with_keys(cls, flatten, unflatten)
    return cls
