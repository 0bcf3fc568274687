"""Callback lists that any thread may change while the engine thread calls them.

The engine thread calls every listener with each fused frame and every
observer with each sensor frame; views, the calibrator and the commands add
and remove theirs from other threads (``ViewHost.detach``,
``LiveCalibrator.stop``). A plain list changed during iteration skips or
repeats callbacks. ``Callbacks`` is copy-on-write: each change builds a new
tuple under a lock, and a call walks the tuple it started with, so adding
or removing is safe from any thread and never blocks the engine.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Callable, Iterable, Iterator

log = logging.getLogger("stage.engine")


class Callbacks:
    """A list-like, copy-on-write sequence of callables (see the module docstring)."""

    def __init__(self, what: str, items: Iterable[Callable[[Any], None]] = ()) -> None:
        self.what = what
        self._items: tuple[Callable[[Any], None], ...] = tuple(items)
        self._lock = threading.Lock()

    # ------------------------------------------------------------ changing (any thread)
    def append(self, fn: Callable[[Any], None]) -> None:
        with self._lock:
            self._items = self._items + (fn,)

    def remove(self, fn: Callable[[Any], None]) -> None:
        """Remove ``fn``; ValueError if it is not there (as list.remove)."""
        with self._lock:
            items = list(self._items)
            items.remove(fn)
            self._items = tuple(items)

    def discard(self, fn: Callable[[Any], None]) -> None:
        """Remove ``fn`` if it is there."""
        try:
            self.remove(fn)
        except ValueError:
            pass

    def extend(self, fns: Iterable[Callable[[Any], None]]) -> None:
        fns = tuple(fns)
        with self._lock:
            self._items = self._items + fns

    def __iadd__(self, fns: Iterable[Callable[[Any], None]]) -> "Callbacks":
        self.extend(fns)
        return self

    def __setitem__(self, index: slice, fns: Iterable[Callable[[Any], None]]) -> None:
        if not isinstance(index, slice):
            raise TypeError("only slice assignment (callbacks[:] = [...]) is supported")
        with self._lock:
            items = list(self._items)
            items[index] = list(fns)
            self._items = tuple(items)

    # ------------------------------------------------------------ reading
    def __iter__(self) -> Iterator[Callable[[Any], None]]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def __bool__(self) -> bool:
        return bool(self._items)

    def __contains__(self, fn: object) -> bool:
        return fn in self._items

    def __eq__(self, other: object) -> bool:
        if isinstance(other, Callbacks):
            return self._items == other._items
        if isinstance(other, (list, tuple)):
            return list(self._items) == list(other)
        return NotImplemented

    def __repr__(self) -> str:
        return f"Callbacks({self.what!r}, {list(self._items)!r})"

    # ------------------------------------------------------------ calling (engine thread)
    def call(self, arg: object) -> None:
        """Call each callback with ``arg``; one that raises is logged and removed."""
        for callback in self._items:
            try:
                callback(arg)
            except Exception:
                log.exception("%s %r raised; it is disabled", self.what, callback)
                self.discard(callback)
