"""TRC marker takes (the OpenSim / Motion Analysis tab-separated text format).

Header: PathFileType line, a names line, a values line (DataRate, CameraRate, NumFrames,
NumMarkers, Units, ...), then ``Frame# Time label ...`` and ``X1 Y1 Z1 ...``; empty cells
are missing markers. The rows must number the header's NumFrames, and the file may not end
inside a row: a truncated take is an error, not a shorter take.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livecap.core.take import Take
from livecap.core.units import to_mm
from transport.errors import TakeFileError
from transport.textlines import CELL, HEADER_LINE, bounded_line, bounded_lines


def read_trc(path: str | Path) -> Take:
    path = Path(path)
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:  # line by line: memory follows the rows
            head = [bounded_line(fh, path, HEADER_LINE, f"header line {i + 1}") for i in range(5)]
            if not head[0].startswith("PathFileType") or not head[4]:
                raise TakeFileError(f"{path}: not a TRC file (no PathFileType header)")
            return _read_rows(path, head, fh)
    except (OSError, UnicodeDecodeError) as exc:
        raise TakeFileError(f"{path}: cannot read TRC ({exc})") from None


def _read_rows(path: Path, head: list[str], fh) -> Take:
    keys = head[1].rstrip("\r\n").split("\t")
    vals = head[2].rstrip("\r\n").split("\t")
    meta = dict(zip([k.strip() for k in keys], [v.strip() for v in vals], strict=False))
    try:
        rate = float(meta["DataRate"])
        n_markers = int(meta["NumMarkers"])
        units = meta.get("Units", "mm")
        scale = to_mm(1.0, units)
    except (KeyError, ValueError) as exc:
        raise TakeFileError(f"{path}: bad TRC header ({str(exc)[:200]})") from None
    if not (np.isfinite(rate) and rate > 0) or n_markers <= 0:
        raise TakeFileError(f"{path}: DataRate {rate} / NumMarkers {n_markers} is not a usable take")
    names = [c.strip() for c in head[3].split("\t")[2:]]
    labels = [c for c in names if c][:n_markers]
    if len(labels) != n_markers:
        raise TakeFileError(f"{path}: header declares {n_markers} markers, names line has {len(labels)}")
    declared = _declared_frames(path, meta)
    rows = []
    frames = []
    for lineno, line in bounded_lines(fh, path, CELL * (2 + 3 * n_markers) + 256, 6):
        if not line.strip():
            continue
        if declared is not None and len(rows) == declared:  # refused at the first extra row, not after reading them all
            raise TakeFileError(f"{path}:{lineno}: more data rows than the header's NumFrames {declared}")
        cells = line.rstrip("\r\n").split("\t")
        if len(cells) < 2:
            raise TakeFileError(f"{path}:{lineno}: short data row")
        if not line.endswith("\n") and len(cells) < 2 + 3 * n_markers:
            raise TakeFileError(f"{path}:{lineno}: the file ends inside a row ({len(cells)} of {2 + 3 * n_markers} "
                                f"cells): truncated; not read as a shorter take")
        row = np.full(3 * n_markers, np.nan)
        for j, cell in enumerate(cells[2:2 + 3 * n_markers]):
            cell = cell.strip()
            if cell:
                try:
                    row[j] = float(cell)
                except ValueError:
                    raise TakeFileError(f"{path}:{lineno}: {_short(cell)} is not a number") from None
        try:
            frames.append(int(float(cells[0])))
        except (ValueError, OverflowError):
            raise TakeFileError(f"{path}:{lineno}: frame number {_short(cells[0])} is not an integer") from None
        rows.append(row)
    if not rows:
        raise TakeFileError(f"{path}: no data rows")
    if declared is not None and declared != len(rows):
        raise TakeFileError(f"{path}: header's NumFrames is {declared} but the file holds {len(rows)} data rows"
                            + (" (truncated?)" if declared > len(rows) else ""))
    xyz = np.array(rows).reshape(len(rows), n_markers, 3) * scale
    return Take(labels, xyz, np.isfinite(xyz).all(axis=2), rate, frames[0])


def _short(cell: str) -> str:
    return repr(cell) if len(cell) <= 40 else f"{cell[:20]!r}... ({len(cell)} characters)"


def _declared_frames(path: Path, meta: dict[str, str]) -> int | None:
    """The header's NumFrames, which the rows must match: a truncated file or a lying header is
    refused rather than read as a shorter take."""
    if "NumFrames" not in meta:
        return None
    try:
        n = int(meta["NumFrames"])
    except ValueError:
        raise TakeFileError(f"{path}: header's NumFrames {meta['NumFrames']!r} is not a frame count") from None
    if n < 0:
        raise TakeFileError(f"{path}: header's NumFrames is {n}")
    return n


def write_trc(take: Take, path: str | Path) -> None:
    path = Path(path)
    n, t = take.n_markers, take.n_frames
    out = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{take.rate:g}\t{take.rate:g}\t{t}\t{n}\tmm\t{take.rate:g}\t{take.first_frame + 1}\t{t}",
        "Frame#\tTime\t" + "\t\t\t".join(take.labels) + "\t\t",
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(n)),
        "",
    ]
    for i in range(t):
        cells = [
            "" if not take.valid[i, j] else f"{take.positions[i, j, k]:.5f}"
            for j in range(n) for k in range(3)
        ]
        out.append(f"{take.first_frame + i + 1}\t{i / take.rate:.6f}\t" + "\t".join(cells))
    path.write_text("\n".join(out) + "\n")
