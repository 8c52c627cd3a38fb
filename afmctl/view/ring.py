"""A bounded ring of numbered points, read by several clients each at its own pace."""
from __future__ import annotations

import threading
from collections import deque
from collections.abc import Iterable
from typing import Any


class Ring:
    """The last ``maxlen`` points appended, each numbered 0, 1, 2, ... in order.

    A reader keeps the number it has read up to and asks :meth:`since` for what came
    after; a reader that fell further behind than ``maxlen`` gets the oldest points still
    held (the rest are gone: memory never grows). Thread-safe.
    """

    def __init__(self, maxlen: int) -> None:
        if maxlen < 1:
            raise ValueError(f"maxlen: {maxlen} must be at least 1")
        self._items: deque[Any] = deque(maxlen=maxlen)
        self._next = 0
        self._lock = threading.Lock()

    @property
    def next_index(self) -> int:
        """The number the next appended point will get (= points appended so far)."""
        return self._next

    def __len__(self) -> int:
        return len(self._items)

    def extend(self, points: Iterable[Any]) -> None:
        with self._lock:
            for p in points:
                self._items.append(p)
                self._next += 1

    def since(self, index: int) -> tuple[list[Any], int]:
        """``(points numbered >= index still held, the index to ask for next time)``."""
        with self._lock:
            held = len(self._items)
            new = self._next - max(index, 0)
            if new <= 0:
                return [], self._next
            start = held - min(new, held)
            return [self._items[i] for i in range(start, held)], self._next
