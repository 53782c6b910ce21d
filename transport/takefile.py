"""Read and write a marker take by file extension (.c3d, .trc, .csv)."""

from __future__ import annotations

from pathlib import Path

from livecap.core.take import Take
from transport.c3d import read_c3d, write_c3d
from transport.csv_take import read_csv_take, write_csv_take
from transport.errors import TakeFileError
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
    return reader(path)


def write_take(take: Take, path: str | Path) -> None:
    path = Path(path)
    writer = WRITERS.get(path.suffix.lower())
    if writer is None:
        raise TakeFileError(f"{path}: unknown take format (expected one of {sorted(WRITERS)})")
    writer(take, path)
