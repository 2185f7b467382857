"""Compiled programs kept per object identity, for eager calls of functions that trace a ``lax.scan``.

A :class:`~gmjax.filters.Filter` or :class:`~gmjax.models.Scenario` holds Python callables, so it is
neither a ``jit`` argument nor hashable. Called eagerly, :func:`gmjax.filters.run` and
:func:`gmjax.models.simulate` would trace and compile their ``lax.scan`` afresh on every call (a second
or more for a GSF, where the compiled program runs in milliseconds). :class:`IdentityCache` keeps one
``jax.jit`` per tuple of owning objects, holding references to them so that their ``id`` cannot be
reused while the entry lives; the least recently used entry goes first.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from typing import Any, Callable, Hashable, TypeVar

__all__ = ["IdentityCache", "CachedProgram"]

V = TypeVar("V")


class IdentityCache:
    """A small LRU map from a tuple of objects (compared by identity) and a hashable tag (compared by
    equality) to a value made on a miss."""

    def __init__(self, maxsize: int = 32):
        self.maxsize = maxsize
        self._entries: OrderedDict[Hashable, tuple[tuple[Any, ...], Any]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, owners: tuple[Any, ...], make: Callable[[], V], tag: Hashable = None) -> V:
        """The value stored for ``(owners, tag)`` (the same objects, by ``is``; an equal tag), or
        ``make()`` stored for them."""
        key = (tuple(id(o) for o in owners), tag)
        with self._lock:
            hit = self._entries.get(key)
            if hit is not None and all(a is b for a, b in zip(hit[0], owners)):
                self._entries.move_to_end(key)
                return hit[1]
        value = make()  # outside the lock: two threads missing at once both make one, one is kept
        with self._lock:
            self._entries[key] = (owners, value)
            self._entries.move_to_end(key)
            while len(self._entries) > self.maxsize:
                self._entries.popitem(last=False)
        return value

    def __len__(self) -> int:
        return len(self._entries)


class CachedProgram:
    """A jitted function and its compiled executables, one per lowered program text (so a change of
    dtype or configuration that changes the program compiles anew)."""

    def __init__(self, jitted: Any):
        self.jitted = jitted
        self._compiled: dict[str, Any] = {}

    def compile(self, *args) -> tuple[Any, float]:
        """``(executable, seconds spent: lowering, plus compiling when it was not compiled before)``."""
        t0 = time.perf_counter()
        lowered = self.jitted.lower(*args)
        text = lowered.as_text()
        if text not in self._compiled:
            self._compiled[text] = lowered.compile()
        return self._compiled[text], time.perf_counter() - t0
