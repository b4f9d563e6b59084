"""A bounded hand-off from transport callbacks (which must not block) to consumer threads."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Iterator
from typing import Generic, TypeVar

T = TypeVar("T")


class Inbox(Generic[T]):
    """Bounded FIFO: ``push`` never blocks (drops the oldest item when full, counted in
    ``dropped``); ``pop`` waits up to ``timeout`` seconds."""

    def __init__(self, maxlen: int = 1024) -> None:
        if maxlen < 1:
            raise ValueError(f"maxlen: must be >= 1, got {maxlen}")
        self._items: deque[T] = deque()
        self._maxlen = maxlen
        self._cond = threading.Condition()
        self._closed = False
        self.dropped = 0

    def push(self, item: T) -> None:
        with self._cond:
            if len(self._items) >= self._maxlen:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cond.notify_all()

    def pop(self, timeout: float | None = None) -> T | None:
        """Oldest item, or None after ``timeout`` seconds (None = wait forever) or on close."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._items:
                if self._closed:
                    return None
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return self._items.popleft()

    def drain(self) -> list[T]:
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    def iterate(self, timeout: float | None = None) -> Iterator[T]:
        """Yield items as they come; stop after ``timeout`` seconds without one, or on close."""
        while True:
            item = self.pop(timeout)
            if item is None:
                return
            yield item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def __len__(self) -> int:
        return len(self._items)
