"""Frozen dataclasses that are JAX pytrees, with static (hashable, compile-time) fields.

Configs of reducers and filters use them: sizes and iteration counts are ``static_field()`` (part of
the tree structure, so changing them recompiles), thresholds are ordinary fields (leaves, so
``jax.grad`` and optax reach them and changing them does not recompile).
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

import jax

__all__ = ["pytree_dataclass", "static_field"]

T = TypeVar("T")


def static_field(default: Any = dataclasses.MISSING, **kwargs: Any) -> Any:
    """A dataclass field that is static auxiliary data of the pytree (not a leaf)."""
    metadata = dict(kwargs.pop("metadata", {}) or {}, static=True)
    return dataclasses.field(default=default, metadata=metadata, **kwargs)


def pytree_dataclass(cls: type[T]) -> type[T]:
    """Decorate ``cls`` as a frozen dataclass registered as a pytree.

    Fields declared with :func:`static_field` go into the tree definition; the rest are children.
    """
    cls = dataclasses.dataclass(frozen=True)(cls)
    fields = dataclasses.fields(cls)
    data_names = [f.name for f in fields if not f.metadata.get("static", False)]
    meta_names = [f.name for f in fields if f.metadata.get("static", False)]
    return jax.tree_util.register_dataclass(cls, data_fields=data_names, meta_fields=meta_names)
