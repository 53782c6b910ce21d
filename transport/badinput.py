"""Bad input is counted by kind and skipped, never fatal: a live session keeps running.

One :class:`BadInput` per source. Each skip bumps a counter and logs at most one line per
``interval`` seconds per kind (with how many were suppressed), so a flood of garbage cannot
flood the log or slow the solver.
"""

from __future__ import annotations

import logging
import time
from collections import Counter

import numpy as np

from livecap.core.take import MarkerFrame

log = logging.getLogger("livecap.input")

KINDS = ("short", "malformed", "version", "nonfinite", "unknown_label", "duplicate_label", "unknown_layout",
         "duplicate_frame", "stale", "overrun")


class BadInput:
    def __init__(self, where: str = "input", interval: float = 2.0) -> None:
        self.where = where
        self.interval = interval
        self.counts: Counter[str] = Counter()
        self._last_log: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()

    def skip(self, kind: str, detail: str) -> None:
        self.counts[kind] += 1
        now = time.monotonic()
        if now - self._last_log.get(kind, -1e9) >= self.interval:
            extra = f" ({self._suppressed[kind]} more since last report)" if self._suppressed[kind] else ""
            log.warning("%s: skipped %s frame: %s%s", self.where, kind, detail, extra)
            self._last_log[kind] = now
            self._suppressed[kind] = 0
        else:
            self._suppressed[kind] += 1

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def as_dict(self) -> dict[str, int]:
        return dict(self.counts)


class FrameOrder:
    """Rejects duplicate and stale (older than the newest seen) frame numbers: a stream that
    goes back in time would make every temporal solver see negative velocities."""

    def __init__(self) -> None:
        self.last: int | None = None

    def check(self, frame: int) -> str | None:
        if self.last is not None:
            if frame == self.last:
                return "duplicate_frame"
            if frame < self.last:
                return "stale"
        self.last = frame
        return None


class LabelMap:
    """Map a packet's labels onto the session's label order (cached per label list)."""

    def __init__(self, labels: list[str]) -> None:
        self.labels = list(labels)
        self._where = {lab: i for i, lab in enumerate(self.labels)}
        self._cache: dict[tuple[str, ...], np.ndarray | str] = {}

    def index(self, labels: list[str]) -> np.ndarray:
        """Target index of each incoming label; raises KeyError naming an unknown label."""
        key = tuple(labels)
        hit = self._cache.get(key)
        if hit is None:
            unknown = [lab for lab in labels if lab not in self._where]
            hit = f"unknown labels {unknown[:5]}" if unknown else np.array([self._where[lab] for lab in labels],
                                                                          dtype=np.int64)
            if len(self._cache) < 64:
                self._cache[key] = hit
        if isinstance(hit, str):
            raise KeyError(hit)
        return hit

    def frame(self, frame: int, timestamp: float, labels: list[str], positions: np.ndarray,
              valid: np.ndarray) -> MarkerFrame:
        idx = self.index(labels)
        n = len(self.labels)
        pos = np.zeros((n, 3))
        val = np.zeros(n, dtype=bool)
        pos[idx] = positions
        val[idx] = valid
        return MarkerFrame(frame, timestamp, pos, val)
