"""CSV marker takes: ``# rate=<Hz> units=<mm|cm|m>`` then a header ``frame,time,<label>.x,<label>.y,<label>.z...``.

Empty or NaN cells are missing markers.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from livecap.core.take import Take
from livecap.core.units import to_mm
from transport.errors import TakeFileError


def read_csv_take(path: str | Path) -> Take:
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            first = fh.readline()
            meta = dict(kv.split("=", 1) for kv in first.lstrip("#").split() if "=" in kv)
            if not first.startswith("#") or "rate" not in meta or "units" not in meta:
                raise TakeFileError(f"{path}: first line must be '# rate=<Hz> units=<mm|cm|m>'")
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise TakeFileError(f"{path}: cannot read CSV take ({exc})") from None
    if not rows:
        raise TakeFileError(f"{path}: no header row")
    header, data = rows[0], [r for r in rows[1:] if r]
    cols = header[2:]
    if len(cols) % 3 or any(not c.endswith((".x", ".y", ".z")) for c in cols):
        raise TakeFileError(f"{path}: columns after frame,time must be <label>.x,<label>.y,<label>.z")
    labels = [c[:-2] for c in cols[::3]]
    try:
        rate, scale = float(meta["rate"]), to_mm(1.0, meta["units"])
        arr = np.array([[float(c) if c.strip() else np.nan for c in r[2:]] for r in data])
        frames = [int(float(r[0])) for r in data]
    except ValueError as exc:
        raise TakeFileError(f"{path}: {exc}") from None
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
