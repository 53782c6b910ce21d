"""Marker data in memory: one frame (``MarkerFrame``) and a whole recorded take (``Take``).

Positions are millimetres. A missing marker has ``valid=False`` and position 0; NaN never
leaves the file readers.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np


@dataclass
class MarkerFrame:
    frame: int
    timestamp: float
    positions: np.ndarray  # n x 3, mm
    valid: np.ndarray  # n bool
    received: float | None = None  # wall clock (time.time()) when livecap received it: the clock timecode's anchor


@dataclass
class Take:
    labels: list[str]
    positions: np.ndarray  # T x n x 3, mm
    valid: np.ndarray  # T x n bool
    rate: float
    first_frame: int = 0

    def __post_init__(self) -> None:
        self.positions = np.asarray(self.positions, dtype=np.float64)
        self.valid = np.asarray(self.valid, dtype=bool)
        finite = np.isfinite(self.positions).all(axis=2)
        self.valid = self.valid & finite
        self.positions = np.where(self.valid[..., None], self.positions, 0.0)
        if self.positions.shape[:2] != self.valid.shape or self.positions.shape[1] != len(self.labels):
            raise ValueError("take arrays do not match its labels")
        if not 0 < self.rate < float("inf"):
            raise ValueError(f"take rate must be positive, got {self.rate}")

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def n_markers(self) -> int:
        return len(self.labels)

    @property
    def duration(self) -> float:
        return self.n_frames / self.rate

    def frames(self) -> Iterator[MarkerFrame]:
        for i in range(self.n_frames):
            yield MarkerFrame(self.first_frame + i, i / self.rate, self.positions[i], self.valid[i])

    def select(self, labels: Sequence[str]) -> Take:
        """The take with markers in ``labels`` order; labels it lacks are missing throughout."""
        where = {lab: i for i, lab in enumerate(self.labels)}
        src = np.array([where.get(lab, -1) for lab in labels], dtype=np.int64)
        have = src >= 0
        pos = np.zeros((self.n_frames, len(labels), 3))
        val = np.zeros((self.n_frames, len(labels)), dtype=bool)
        pos[:, have] = self.positions[:, src[have]]
        val[:, have] = self.valid[:, src[have]]
        return Take(list(labels), pos, val, self.rate, self.first_frame)

    def slice(self, start: int, stop: int | None = None) -> Take:
        stop = self.n_frames if stop is None else stop
        return Take(self.labels, self.positions[start:stop], self.valid[start:stop], self.rate,
                    self.first_frame + start)
