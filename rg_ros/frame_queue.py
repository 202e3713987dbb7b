"""What the node hands the map worker: one converted `Frame`, through a bounded `FrameQueue` that
drops the oldest frame when full (drops are counted), so the callbacks never wait for mapping."""
from __future__ import annotations

import collections
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class Frame:
    """One synchronised, converted frame (what the mapper takes)."""

    rgb: np.ndarray            # [H, W, 3] uint8 RGB
    depth: np.ndarray          # [H, W] float32 metres, 0 = invalid
    K: np.ndarray              # [3, 3] float64
    cam_to_world: np.ndarray   # [4, 4] float64, OpenCV (optical frame) axes, map frame
    stamp: float               # seconds
    frame_id: str = ""         # the camera's optical frame


class FrameQueue:
    """Bounded FIFO: `put` on a full queue drops the oldest item and counts it."""

    def __init__(self, maxsize: int):
        if maxsize < 1:
            raise ValueError(f"queue size must be >= 1, got {maxsize}")
        self.maxsize = int(maxsize)
        self._items: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self.dropped = 0
        self.put_count = 0

    def put(self, item: Any) -> bool:
        """Queue `item`; returns True if the oldest queued item was dropped to make room."""
        with self._cond:
            dropped = len(self._items) >= self.maxsize
            if dropped:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self.put_count += 1
            self._cond.notify()
            return dropped

    def get(self, timeout: float | None = None) -> Any | None:
        """The oldest item, or None after `timeout` seconds (0: do not wait)."""
        with self._cond:
            if not self._items and timeout != 0:
                self._cond.wait(timeout)
            return self._items.popleft() if self._items else None

    def clear(self) -> int:
        """Drop every queued item (counted as dropped); returns how many."""
        with self._cond:
            n = len(self._items)
            self._items.clear()
            self.dropped += n
            return n

    def wake(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)
