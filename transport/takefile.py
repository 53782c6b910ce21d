"""Read and write a marker take by file extension (.c3d, .trc, .csv)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livecap.core.take import Take
from transport.c3d import read_c3d, write_c3d
from transport.csv_take import read_csv_take, write_csv_take
from transport.errors import TakeFileError
from transport.llf_csv import is_llf_csv
from transport.trc import read_trc, write_trc

READERS = {".c3d": read_c3d, ".trc": read_trc, ".csv": read_csv_take}
WRITERS = {".c3d": write_c3d, ".trc": write_trc, ".csv": write_csv_take}


def read_take(path: str | Path) -> Take:
    path = Path(path)
    if not path.is_file():
        raise TakeFileError(f"{path}: no such take file")
    reader = READERS.get(path.suffix.lower())
    if reader is None:
        raise TakeFileError(f"{path}: unknown take format (expected one of {sorted(READERS)})")
    if is_weights_take(path):
        raise TakeFileError(f"{path}: a Live Link Face CSV holds ARKit weights, not markers (livecap solve, "
                            "replay and review read it with --rig; docs/iphone.md)")
    return reader(path)


def is_weights_take(path: str | Path) -> bool:
    """A take of weights rather than markers: the Live Link Face app's CSV (transport/llf_csv.py)."""
    return Path(path).suffix.lower() == ".csv" and is_llf_csv(path)


FACE_MM = (20.0, 600.0)  # a face's markers span ~100-300 mm; outside this range the units are suspect


def size_problem(take: Take) -> str | None:
    """Why the markers cannot be a face at this scale (e.g. mm data labelled ``units=m``, scaled
    x1000: a face metres wide), or None when their median span over the take is plausible."""
    span = []
    for i in np.linspace(0, take.n_frames - 1, min(take.n_frames, 20)).astype(int):
        p = take.positions[i][take.valid[i]]
        if len(p) >= 3:
            span.append(float(np.linalg.norm(p.max(0) - p.min(0))))
    if not span:
        return None
    size = float(np.median(span))
    if FACE_MM[0] <= size <= FACE_MM[1]:
        return None
    return f"markers span {size:.4g} mm across (a face spans ~100-300 mm): are the file's units right?"


def write_take(take: Take, path: str | Path) -> None:
    path = Path(path)
    writer = WRITERS.get(path.suffix.lower())
    if writer is None:
        raise TakeFileError(f"{path}: unknown take format (expected one of {sorted(WRITERS)})")
    writer(take, path)
