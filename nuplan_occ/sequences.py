"""Read-only sequences whose elements are made when asked for: a pass over a scene's sweeps through one
holds one sweep at a time (the scene's clouds and per-sweep stage outputs are kept on disk)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any


class MappedSequence(Sequence):
    """fn(item) for each of `items`, computed on every access (nothing is kept)."""

    def __init__(self, items: Sequence, fn: Callable[[Any], Any]) -> None:
        self._items, self._fn = items, fn

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[j] for j in range(*k.indices(len(self)))]
        return self._fn(self._items[k])
