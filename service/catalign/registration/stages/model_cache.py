"""Per-model pieces a stage computes once and keeps: the matching subset, the surface check, the
ICP surface with its KD-tree and normals (about 1.1 MB a model in all).

A worker serving a large library would otherwise keep the pieces of every model it was ever
asked about (1.1 GB for 1000 models); :class:`ModelCache` keeps the ``capacity`` most recently
used and drops the others, which are computed again if asked for (about 20 ms a model).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Generic, TypeVar

V = TypeVar("V")


class ModelCache(Generic[V]):
    """Values by model id, at most ``capacity`` of them (None: no bound), least recently used
    dropped first. Safe to share between threads; ``make`` runs outside the lock, so two
    threads may both compute a missing value (the last one is kept)."""

    def __init__(self, capacity: int | None) -> None:
        if capacity is not None and capacity < 1:
            raise ValueError(f"a model cache holds at least one model, not {capacity}")
        self.capacity = capacity
        self._items: OrderedDict[str, V] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, model_id: str, make: Callable[[], V]) -> V:
        """The value for ``model_id``, made by ``make()`` when it is not kept."""
        with self._lock:
            if model_id in self._items:
                self._items.move_to_end(model_id)
                return self._items[model_id]
        value = make()
        with self._lock:
            self._items[model_id] = value
            self._items.move_to_end(model_id)
            while self.capacity is not None and len(self._items) > self.capacity:
                self._items.popitem(last=False)
        return value

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, model_id: object) -> bool:
        return model_id in self._items
