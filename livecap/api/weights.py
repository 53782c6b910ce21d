"""A solved take as one small typed container, with its writers (transport's, so the bytes are the
commands')."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livecap.core.result import SolveResult
from livecap.core.rig import Rig


@dataclass(frozen=True)
class Weights:
    """Blendshape weight curves of one take.

    ``values`` is frames x shapes in ``names`` order; ``times`` seconds from the take's start;
    ``head_rotation`` quaternions (x, y, z, w) and ``head_translation`` mm, raw = R @ stabilised + t;
    ``residual`` the RMS marker fit error per frame in mm (NaN where no marker was seen): the quality.
    """

    names: list[str]
    times: np.ndarray
    values: np.ndarray
    head_rotation: np.ndarray
    head_translation: np.ndarray
    residual: np.ndarray
    rate: float
    first_frame: int = 0

    def __len__(self) -> int:
        return len(self.values)

    def __getitem__(self, name: str) -> np.ndarray:
        """One shape's curve by name."""
        return self.values[:, self.names.index(name)]

    def results(self) -> Iterator[SolveResult]:
        """Per-frame results, what a live session publishes (feed them to any sink)."""
        for i, w in enumerate(self.values):
            yield SolveResult(self.first_frame + i, float(self.times[i]), self.names, w, self.head_rotation[i],
                              self.head_translation[i], float(np.nan_to_num(self.residual[i])))

    def to_csv(self, path: str | Path) -> Path:
        """The weights CSV ``livecap solve --out X.csv`` writes (frame, time, one column per shape)."""
        from transport.weights_csv import write_weights_csv

        write_weights_csv(path, self.names, self.values, self.rate, self.first_frame)
        return Path(path)

    def to_llf_csv(self, path: str | Path, *, mapping: dict | None = None) -> Path:
        """A Live Link Face CSV (ARKit's 52 curves and head angles); ``mapping`` maps rig shapes to ARKit
        names when the rig's are not ARKit's (docs/protocol.md)."""
        from transport.recorders import CsvRecorder

        self._record(CsvRecorder(path, rate=self.rate, layout="livelinkface", mapping=mapping))
        return Path(path)

    def to_jsonl(self, path: str | Path) -> Path:
        """One JSON object per frame, what ``livecap run --record-jsonl`` writes."""
        from transport.recorders import JsonlRecorder

        self._record(JsonlRecorder(path))
        return Path(path)

    def to_glb(self, path: str | Path, rig: Rig, *, neutral_seconds: float = 1.0) -> Path:
        """A .glb of ``rig`` animated by these weights and the head pose (relative to its mean over the first
        ``neutral_seconds``), what ``livecap solve --out X.glb`` writes."""
        from livecap.offline.glb import write_solved_glb
        from livecap.offline.solve import SolvedTake

        solved = SolvedTake(self.names, self.values, self.head_rotation, self.head_translation, np.zeros(0),
                            np.zeros(0), self.rate, self.first_frame, 0.0)
        write_solved_glb(path, rig, solved, max(1, int(neutral_seconds * self.rate)))
        return Path(path)

    def _record(self, sink) -> None:
        try:
            for result in self.results():
                sink.publish(result)
        finally:
            sink.close()
