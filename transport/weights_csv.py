"""Weight curves as CSV: ``frame,time,<shape>...``, one row per frame (what animators edit)."""

from __future__ import annotations

import csv
import io
from itertools import chain
from pathlib import Path

import numpy as np

ROWS_PER_BLOCK = 4096  # rows formatted per call: bounded memory on long takes


def write_weights_csv(path: str | Path, names: list[str], weights: np.ndarray, rate: float,
                      first_frame: int = 0) -> None:
    """Rows ``frame, i / rate, weights`` to 6 decimals, CRLF-terminated as ``csv.writer`` writes them, UTF-8.

    A block of rows is formatted by one compiled call (``transport.fixed_point``), byte for byte what ``%``
    writes; a block holding a value it cannot be sure of (non-finite, huge, a product a hair from half-way)
    is formatted by one ``%`` over a repeated row template instead (numbers never need CSV quoting).
    """
    from transport.fixed_point import BYTES_PER_INT, BYTES_PER_VALUE, format_rows

    W = np.asarray(weights, dtype=np.float64)
    T = len(W)
    W = np.ascontiguousarray(W.reshape(T, -1))
    header = io.StringIO()
    csv.writer(header).writerow(["frame", "time", *names])
    row = "%d,%.6f" + ",%.6f" * W.shape[1] + "\r\n"
    buf = np.empty(min(T, ROWS_PER_BLOCK) * (BYTES_PER_INT + BYTES_PER_VALUE * (1 + W.shape[1]) + 2), np.uint8)
    with open(path, "wb") as fh:
        fh.write(header.getvalue().encode("utf-8"))
        for s in range(0, T, ROWS_PER_BLOCK):
            e = min(T, s + ROWS_PER_BLOCK)
            frames = np.arange(first_frame + s, first_frame + e, dtype=np.int64)
            times = np.arange(s, e) / rate
            n = format_rows(frames, times, W[s:e], buf)
            if n >= 0:
                fh.write(buf[:n].data)
                continue
            values = chain.from_iterable((f, t, *w) for f, t, w in zip(frames.tolist(), times.tolist(),
                                                                         W[s:e].tolist(), strict=True))
            fh.write(((row * (e - s)) % tuple(values)).encode("ascii"))


def read_weights_csv(path: str | Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Shape names, weights (T x m) and times (T)."""
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    if not rows or rows[0][:2] != ["frame", "time"]:
        raise ValueError(f"{path}: not a weights CSV (header must start with frame,time)")
    data = np.array([[float(c) for c in r] for r in rows[1:] if r]).reshape(-1, len(rows[0]))
    return rows[0][2:], data[:, 2:], data[:, 1]
