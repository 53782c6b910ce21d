"""Weight curves as CSV: ``frame,time,<shape>...``, one row per frame (what animators edit)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


def write_weights_csv(path: str | Path, names: list[str], weights: np.ndarray, rate: float,
                      first_frame: int = 0) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "time", *names])
        for i, row in enumerate(np.asarray(weights)):
            w.writerow([first_frame + i, f"{i / rate:.6f}", *(f"{v:.6f}" for v in row)])


def read_weights_csv(path: str | Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Shape names, weights (T x m) and times (T)."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows or rows[0][:2] != ["frame", "time"]:
        raise ValueError(f"{path}: not a weights CSV (header must start with frame,time)")
    data = np.array([[float(c) for c in r] for r in rows[1:] if r]).reshape(-1, len(rows[0]))
    return rows[0][2:], data[:, 2:], data[:, 1]
