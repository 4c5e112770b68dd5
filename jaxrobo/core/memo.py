"""Values remembered for objects while they live, found by the objects themselves (their identity, not equality).

Why: the end of a run copies the same device arrays twice, from the closing checkpoint's thread and for the
run's result; each copy of gigabytes should be made once. An array is not hashable by value, and its ``id`` alone
could name another array once it is freed, so an entry holds a weak reference to each of its objects and is
dropped when any of them dies.

Public surface: :class:`IdentityMemo`.
"""
from __future__ import annotations

import threading
import weakref
from typing import Any, Callable


class IdentityMemo:
    """Values keyed on live objects (one or several; any weakly referable object). ``latest_only``: at most one
    entry, the last put (a run's end copies one set of arrays). Callers that must compute a value once across
    threads hold :attr:`lock` around their :meth:`get` and :meth:`put` (:meth:`get_or_make` does)."""

    def __init__(self, *, latest_only: bool = False) -> None:
        self.lock = threading.Lock()
        self._latest_only = latest_only
        self._entries: dict[tuple[int, ...], tuple[list[weakref.ref], Any]] = {}

    def get(self, *objs: Any, default: Any = None) -> Any:
        """The value put for exactly these objects (in this order) while all of them live, else ``default``."""
        hit = self._entries.get(tuple(id(x) for x in objs))
        if hit is None or len(hit[0]) != len(objs) or any(ref() is not x for ref, x in zip(hit[0], objs)):
            return default
        return hit[1]

    def put(self, objs: tuple[Any, ...] | list[Any], value: Any) -> Any:
        """Remember ``value`` for ``objs`` until one of them dies (or, ``latest_only``, the next put); returns it."""
        key = tuple(id(x) for x in objs)
        if self._latest_only:
            self._entries.clear()
        # The callback runs as the object dies, before its id can name another object.
        self._entries[key] = ([weakref.ref(x, lambda _, key=key: self._entries.pop(key, None)) for x in objs], value)
        return value

    def get_or_make(self, objs: tuple[Any, ...] | list[Any], make: Callable[[], Any]) -> Any:
        """The value for ``objs``, made by ``make()`` (under :attr:`lock`, so once across threads) if none is."""
        missing = object()
        with self.lock:
            hit = self.get(*objs, default=missing)
            return self.put(objs, make()) if hit is missing else hit

    def __len__(self) -> int:
        return len(self._entries)
