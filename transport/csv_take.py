"""CSV marker takes: ``# rate=<Hz> units=<mm|cm|m>`` then a header ``frame,time,<label>.x,<label>.y,<label>.z...``.

Empty or NaN cells are missing markers. Every row has the header's cells: a file that ends inside a
row is an error, not a shorter take.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from livecap.core.take import Take
from livecap.core.units import to_mm
from transport.errors import TakeFileError
from transport.textlines import CELL, HEADER_LINE, bounded_line, bounded_lines


def read_csv_take(path: str | Path) -> Take:
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            first = bounded_line(fh, path, HEADER_LINE, "line 1")
            meta = dict(kv.split("=", 1) for kv in first.lstrip("#").split() if "=" in kv)
            if not first.startswith("#") or "rate" not in meta or "units" not in meta:
                raise TakeFileError(f"{path}: first line must be '# rate=<Hz> units=<mm|cm|m>'")
            rows = list(csv.reader([bounded_line(fh, path, HEADER_LINE, "line 2")]))
            if rows:
                limit = CELL * len(rows[0]) + 256
                rows += csv.reader(line for _, line in bounded_lines(fh, path, limit, 3))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:  # csv.Error: a field over csv's 128 kB limit
        raise TakeFileError(f"{path}: cannot read CSV take ({exc})") from None
    if not rows:
        raise TakeFileError(f"{path}: no header row")
    header, data = rows[0], [r for r in rows[1:] if r]
    cols = header[2:]
    if len(cols) % 3 or any(not c.endswith((".x", ".y", ".z")) for c in cols):
        raise TakeFileError(f"{path}: columns after frame,time must be <label>.x,<label>.y,<label>.z")
    labels = [c[:-2] for c in cols[::3]]
    short = next((i for i, r in enumerate(data) if len(r) != len(header)), None)
    if short is not None:  # the last row short: a truncated file, which is not read as a shorter take
        raise TakeFileError(f"{path}: data row {short + 1} of {len(data)} has {len(data[short])} cells, the header "
                            f"{len(header)}" + (" (the file ends inside it: truncated)" if short == len(data) - 1
                                                else ""))
    try:
        rate, scale = float(meta["rate"]), to_mm(1.0, meta["units"])
        arr = np.array([[float(c) if c.strip() else np.nan for c in r[2:]] for r in data])
        frames = [int(float(r[0])) for r in data]
    except ValueError as exc:  # float()'s message quotes the whole cell, which may be megabytes
        raise TakeFileError(f"{path}: {str(exc)[:200]}") from None
    if not (np.isfinite(rate) and rate > 0):
        raise TakeFileError(f"{path}: rate={meta['rate']} is not a positive finite frame rate")
    if arr.ndim != 2 or arr.shape[1] != len(cols):
        raise TakeFileError(f"{path}: rows do not all have {len(cols) + 2} cells")
    xyz = arr.reshape(len(data), len(labels), 3) * scale
    return Take(labels, xyz, np.isfinite(xyz).all(axis=2), rate, frames[0] if frames else 0)


def write_csv_take(take: Take, path: str | Path) -> None:
    with open(path, "w", newline="") as fh:
        fh.write(f"# rate={take.rate:g} units=mm\n")
        w = csv.writer(fh)
        w.writerow(["frame", "time"] + [f"{lab}.{a}" for lab in take.labels for a in "xyz"])
        for i in range(take.n_frames):
            cells = [
                f"{v:.5f}" if take.valid[i, j] else ""
                for j in range(take.n_markers) for v in take.positions[i, j]
            ]
            w.writerow([take.first_frame + i, f"{i / take.rate:.6f}"] + cells)
