"""Bad input is counted by kind and skipped, never fatal: a live session keeps running.

One :class:`BadInput` per source. Each skip bumps a counter and logs at most one line per
``interval`` seconds per kind (with how many were suppressed), so a flood of garbage cannot
flood the log or slow the solver.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter

import numpy as np

from livecap.core.take import MarkerFrame

log = logging.getLogger("livecap.input")

KINDS = ("short", "malformed", "version", "nonfinite", "unknown_label", "duplicate_label", "unknown_layout",
         "layout_mismatch", "oversize", "duplicate_frame", "out_of_order", "frame_outlier", "overrun")
# Not skips but events, counted beside them: a sender that restarted (its frames are used), and frame
# numbers that never arrived (UDP sources: lost datagrams).
EVENTS = ("stream_restart", "missing")


MISMATCH_PACKETS = 120  # packets naming unknown markers, before any good frame, that end a session


class LabelMismatch(ValueError):
    """The stream's markers are not the session's: every packet names labels the profile/rig lacks."""


class BadInput:
    def __init__(self, where: str = "input", interval: float = 2.0) -> None:
        self.where = where
        self.interval = interval
        self.counts: Counter[str] = Counter()
        self._last_log: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()
        self._lock = threading.Lock()  # a source's reader thread counts too

    def skip(self, kind: str, detail: str) -> None:
        with self._lock:
            self.counts[kind] += 1
        now = time.monotonic()
        if now - self._last_log.get(kind, -1e9) >= self.interval:
            extra = f" ({self._suppressed[kind]} more since last report)" if self._suppressed[kind] else ""
            log.warning("%s: skipped %s frame: %s%s", self.where, kind, detail, extra)
            self._last_log[kind] = now
            self._suppressed[kind] = 0
        else:
            self._suppressed[kind] += 1

    def check_labels_match(self, seen_good: bool, detail: str) -> None:
        """Raise :class:`LabelMismatch` when the first :data:`MISMATCH_PACKETS` packets all named
        unknown labels: a wrong --profile/--rig, which would otherwise publish nothing, silently."""
        if not seen_good and self.counts["unknown_label"] >= MISMATCH_PACKETS:
            raise LabelMismatch(f"{self.where}: the first {self.counts['unknown_label']} packets name markers the "
                                f"profile/rig does not have ({detail}): wrong --profile or --rig for this stream?")

    def event(self, kind: str, detail: str, n: int = 1) -> None:
        """Count ``n`` and log (rate-limited) something that is not a skip, e.g. a sender restart."""
        self.counts[kind] += n
        now = time.monotonic()
        if now - self._last_log.get(kind, -1e9) >= self.interval:
            log.warning("%s: %s: %s", self.where, kind, detail)
            self._last_log[kind] = now

    def in_order(self, order: FrameOrder, frame: int, timestamp: float) -> bool:
        """Check ``frame`` against ``order``; count and log whatever it was. True: use the frame."""
        last, restarts = order.last, order.restarts
        kind = order.check(frame, timestamp)
        if kind:
            self.skip(kind, f"frame {frame} after {last}")
            return False
        if order.restarts != restarts:
            self.event("stream_restart", f"frame {frame} after {last}: a new stream, solving it")
        return True

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def as_dict(self) -> dict[str, int]:
        return dict(self.counts)


class FrameOrder:
    """Frame-number bookkeeping that survives a sender restarting and ignores one lying packet.

    * a frame number at most ``back`` frames older than the newest is a reordered packet:
      ``out_of_order`` (a temporal solver must not see time run backwards);
    * a jump further back, or a timestamp more than ``time_back`` seconds before the newest, is a
      new stream (the sender restarted): ``stream_restart``, and the frame is used;
    * a jump more than ``ahead`` frames forward is held as a candidate and counted as
      ``frame_outlier``; it is adopted only when the next frame continues from it, so a single
      lie (frame 2**40) cannot make every honest frame look old.
    """

    def __init__(self, back: int = 30, ahead: int = 12000, time_back: float = 1.0) -> None:
        self.back = back
        self.ahead = ahead
        self.time_back = time_back
        self.last: int | None = None
        self.last_time: float | None = None
        self.restarts = 0
        self._candidate: int | None = None

    def _accept(self, frame: int, timestamp: float | None) -> None:
        self.last = frame
        self.last_time = timestamp
        self._candidate = None

    def check(self, frame: int, timestamp: float | None = None) -> str | None:
        """None when the frame is to be used; otherwise the bad-input kind to count it under."""
        if self.last is None:
            self._accept(frame, timestamp)
            return None
        if (timestamp is not None and self.last_time is not None
                and timestamp < self.last_time - self.time_back and frame != self.last):
            return self._restart(frame, timestamp)
        d = frame - self.last
        if d == 0:
            return "duplicate_frame"
        if d < -self.back:
            return self._restart(frame, timestamp)
        if d < 0:
            return "out_of_order"
        if d > self.ahead:
            cand = self._candidate
            if cand is not None and 0 < frame - cand <= self.back:
                return self._restart(frame, timestamp)
            self._candidate = frame
            return "frame_outlier"
        self._accept(frame, timestamp)
        return None

    def _restart(self, frame: int, timestamp: float | None) -> None:
        self.restarts += 1
        self._accept(frame, timestamp)
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
            if len(self._cache) < 64 and not isinstance(hit, str):  # never keep a hostile label list
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
