"""Paced replay of a recorded take (C3D / TRC / CSV, or livecap's raw ``.npz`` recording).

Frames come out at the take's rate x ``speed`` against a monotonic clock (a late frame is
sent at once and the schedule is kept, so pacing does not drift), or as fast as possible.
With ``loop`` the take repeats with frame numbers and timestamps that keep increasing, so a
downstream order check and temporal solvers see one continuous stream.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from livecap.core.take import MarkerFrame, Take
from transport.takefile import read_take


def open_take(path: str | Path) -> tuple[Take, np.ndarray, np.ndarray]:
    """A take plus its per-frame numbers and timestamps (exact for raw ``.npz`` recordings)."""
    path = Path(path)
    if path.suffix.lower() == ".npz":
        from transport.recorders import read_marker_recording

        rec = read_marker_recording(path)
        return rec.take, rec.frames, rec.timestamps
    take = read_take(path)
    return take, take.first_frame + np.arange(take.n_frames), np.arange(take.n_frames) / take.rate


class ReplaySource:
    def __init__(self, take: Take, labels: list[str] | None = None, speed: float = 1.0, fast: bool = False,
                 loop: bool = False, start: int | None = None, end: int | None = None,
                 frames: np.ndarray | None = None, timestamps: np.ndarray | None = None) -> None:
        if not speed > 0:
            raise ValueError(f"replay speed must be positive, got {speed}")
        frames = take.first_frame + np.arange(take.n_frames) if frames is None else np.asarray(frames)
        timestamps = np.arange(take.n_frames) / take.rate if timestamps is None else np.asarray(timestamps)
        keep = np.ones(take.n_frames, dtype=bool)
        if start is not None:
            keep &= frames >= start
        if end is not None:
            keep &= frames < end
        if not keep.any():
            raise ValueError(f"no frames of the take lie in [{start}, {end}) "
                             f"(it holds frames {frames[0]}..{frames[-1]})")
        idx = np.flatnonzero(keep)
        take = take.slice(int(idx[0]), int(idx[-1]) + 1)
        self.take = take.select(labels) if labels is not None else take
        self.labels = list(self.take.labels)
        self.frames = frames[idx[0]:idx[-1] + 1]
        self.timestamps = timestamps[idx[0]:idx[-1] + 1]
        self.rate = take.rate
        self.speed, self.fast, self.loop = speed, fast, loop
        self.last_decode_seconds = 0.0
        self._next_due = float("inf")  # perf_counter time the next frame is scheduled for
        self._running = True

    @classmethod
    def open(cls, path: str | Path, labels: list[str] | None = None, **kwargs) -> ReplaySource:
        take, frames, timestamps = open_take(path)
        return cls(take, labels, frames=frames, timestamps=timestamps, **kwargs)

    def pending(self) -> bool:
        """Paced replay only: True when the next frame's time has already come (the consumer is
        behind the schedule). ``--fast`` replay never reports pending frames: all must be solved."""
        return not self.fast and time.perf_counter() >= self._next_due

    def stop(self) -> None:
        self._running = False

    def _wait_until(self, when: float) -> None:
        while self._running:
            left = when - time.perf_counter()
            if left <= 0:
                return
            time.sleep(min(left, 0.05))

    def __iter__(self) -> Iterator[MarkerFrame]:
        n = self.take.n_frames
        period = 1.0 / (self.rate * self.speed)
        span_frames = int(self.frames[-1] - self.frames[0]) + 1
        span_time = n / self.rate
        t0 = time.perf_counter()
        k = 0  # frames emitted so far (across loops): the schedule
        lap = 0
        while self._running:
            for i in range(n):
                if not self._running:
                    return
                if not self.fast:
                    self._wait_until(t0 + k * period)
                    if not self._running:
                        return
                more = self.loop or i + 1 < n
                self._next_due = t0 + (k + 1) * period if more else float("inf")
                yield MarkerFrame(int(self.frames[i]) + lap * span_frames,
                                  float(self.timestamps[i]) + lap * span_time,
                                  self.take.positions[i], self.take.valid[i])
                k += 1
            if not self.loop:
                return
            lap += 1
