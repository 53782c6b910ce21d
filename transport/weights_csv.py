"""Weight curves as CSV: ``frame,time,<shape>...``, one row per frame (what animators edit)."""

from __future__ import annotations

import csv
import io
from itertools import chain
from pathlib import Path

import numpy as np

ROWS_PER_BLOCK = 4096  # rows formatted per string operation: bounded memory on long takes


def write_weights_csv(path: str | Path, names: list[str], weights: np.ndarray, rate: float,
                      first_frame: int = 0) -> None:
    """Rows ``frame, i / rate, weights`` to 6 decimals, CRLF-terminated as ``csv.writer`` writes them.

    The rows are formatted a block at a time by one ``%`` over a repeated row template (numbers
    never need CSV quoting), ten times faster than a ``csv.writer`` call per row, byte for byte the same.
    """
    W = np.asarray(weights)
    T = len(W)
    W = W.reshape(T, -1)
    header = io.StringIO()
    csv.writer(header).writerow(["frame", "time", *names])
    row = "%d,%.6f" + ",%.6f" * W.shape[1] + "\r\n"
    with open(path, "w", newline="") as fh:
        fh.write(header.getvalue())
        for s in range(0, T, ROWS_PER_BLOCK):
            e = min(T, s + ROWS_PER_BLOCK)
            frames = range(first_frame + s, first_frame + e)
            times = (np.arange(s, e) / rate).tolist()
            values = chain.from_iterable((f, t, *w) for f, t, w in zip(frames, times, W[s:e].tolist(), strict=True))
            fh.write((row * (e - s)) % tuple(values))


def read_weights_csv(path: str | Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Shape names, weights (T x m) and times (T)."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows or rows[0][:2] != ["frame", "time"]:
        raise ValueError(f"{path}: not a weights CSV (header must start with frame,time)")
    data = np.array([[float(c) for c in r] for r in rows[1:] if r]).reshape(-1, len(rows[0]))
    return rows[0][2:], data[:, 2:], data[:, 1]
