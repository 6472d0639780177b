"""The simulator's small LRU cache of per-rig, per-map and per-object-set precomputations."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any


class LruCache:
    """A small LRU cache. Identity keys keep a reference to their objects (``anchors``) so an id
    stays unique while it is cached, and a hit must find the very same objects."""

    def __init__(self, size: int) -> None:
        self._size = size
        self._data: OrderedDict[Hashable, tuple[Any, Any]] = OrderedDict()

    def get(self, key: Hashable, anchors: tuple, make: Callable[[], Any]) -> Any:
        hit = self._data.get(key)
        if hit is not None and all(a is b for a, b in zip(hit[0], anchors, strict=True)):
            self._data.move_to_end(key)
            return hit[1]
        value = make()
        self._data[key] = (anchors, value)
        self._data.move_to_end(key)
        while len(self._data) > self._size:
            self._data.popitem(last=False)
        return value
