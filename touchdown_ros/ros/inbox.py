"""Samples received by the node and not yet estimated, in arrival order; thread-safe."""
from __future__ import annotations

import threading
import time

import numpy as np


class Inbox:
    """Samples received and not yet estimated, in arrival order; thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._stamps: list[int] = []
        self._xyz: list[tuple[float, float, float]] = []
        self._blocks: list[tuple[np.ndarray, np.ndarray]] = []
        self.count = 0
        self.oldest_ns = 0  # time.monotonic_ns() when the oldest pending sample arrived

    def add_sample(self, stamp_ns: int, x: float, y: float, z: float) -> int:
        """Add one sample; returns the number pending."""
        with self._lock:
            if not self.count:
                self.oldest_ns = time.monotonic_ns()
            self._stamps.append(stamp_ns)
            self._xyz.append((x, y, z))
            self.count += 1
            return self.count

    def add_block(self, stamps_ns: np.ndarray, xyz: np.ndarray) -> int:
        """Add a batch (after the single samples received before it); returns the number pending."""
        with self._lock:
            if not self.count:
                self.oldest_ns = time.monotonic_ns()
            self._hold_singles()
            self._blocks.append((stamps_ns, xyz))
            self.count += len(stamps_ns)
            return self.count

    def take(self) -> tuple[np.ndarray, np.ndarray, int] | None:
        """(stamps ns, xyz m, arrival of the oldest as time.monotonic_ns()) of everything pending, or None."""
        with self._lock:
            if not self.count:
                return None
            self._hold_singles()
            blocks, self._blocks, self.count = self._blocks, [], 0
            oldest = self.oldest_ns
        if len(blocks) == 1:
            return (*blocks[0], oldest)
        return np.concatenate([b[0] for b in blocks]), np.concatenate([b[1] for b in blocks]), oldest

    def _hold_singles(self) -> None:
        if self._stamps:
            self._blocks.append((np.array(self._stamps, np.int64), np.array(self._xyz)))
            self._stamps, self._xyz = [], []
