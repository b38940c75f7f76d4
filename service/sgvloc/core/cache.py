"""A small least-recently-used cache of things that are costly to build (tracking
submaps, indexed keyframe clouds for ICP)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

T = TypeVar("T")


class BuildCache(Generic[T]):
    """Items by key, least recently used first out, at most ``capacity``. Thread-safe; an
    item is built once even when several threads ask for it at the same time (the others
    wait for that build)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._items: OrderedDict[Hashable, T] = OrderedDict()
        self._lock = threading.Lock()
        self._building: dict[Hashable, threading.Event] = {}

    def get(self, key: Hashable, build: Callable[[], T]) -> T:
        while True:
            with self._lock:
                if key in self._items:
                    self._items.move_to_end(key)
                    return self._items[key]
                waiting = self._building.get(key)
                if waiting is None:
                    self._building[key] = threading.Event()
                    break
            waiting.wait()
        try:
            item = build()
            with self._lock:
                self._items[key] = item
                while len(self._items) > self.capacity:
                    self._items.popitem(last=False)
            return item
        finally:
            with self._lock:
                self._building.pop(key).set()


class FetchCache(Generic[T]):
    """Items by integer id fetched from elsewhere in batches: :meth:`get_many` answers
    the ids it holds and fetches all the others with one call of ``fetch`` (a round trip
    to a store), keeping at most ``capacity`` items, least recently used first out.
    Thread-safe; the fetch runs outside the lock."""

    def __init__(self, fetch: Callable[[list[int]], dict[int, T]], capacity: int) -> None:
        self.fetch = fetch
        self.capacity = capacity
        self._items: OrderedDict[int, T] = OrderedDict()
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    def get_many(self, ids: list[int]) -> dict[int, T]:
        """``{id: item}`` for every id that exists (a missing one is left out)."""
        out: dict[int, T] = {}
        with self._lock:
            for i in ids:
                item = self._items.get(i)
                if item is not None:
                    self._items.move_to_end(i)
                    out[i] = item
            missing = [i for i in ids if i not in out]
            self.hits += len(out)
            self.misses += len(missing)
        if missing:
            fetched = self.fetch(missing)
            out.update(fetched)
            with self._lock:
                self._items.update(fetched)
                while len(self._items) > self.capacity:
                    self._items.popitem(last=False)
        return out

    def __len__(self) -> int:
        return len(self._items)
