"""The review session's edit journal: one line per edit, undo or redo, beside the take.

Edits otherwise live only in the server's memory; a killed server would lose them without a word.
Like the marker recordings' journal (transport/recorders.py) it is append-only and fsync'd after
every line, so each acknowledged edit is on disk. Each line carries a CRC-32 of its JSON text
(``crc32-hex SPACE json``): a torn or flipped line is detected, and it and everything after it
(a corrupt tail) are skipped, counted and cut off before new lines are appended.

The first line is a header with a fingerprint of the solve the edits were made on; a journal
written over another solve (other mode, other weights) is never replayed: :func:`open_journal`
sets it aside under a new name and starts afresh. One server at a time holds a journal (a lock).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import time
import zlib
from pathlib import Path

import numpy as np

from transport.recorders import _fsync_dir  # the marker recordings' own: one folder fsync

MAGIC = "livecap-review-journal"


def fingerprint(names: list[str], weights: np.ndarray) -> str:
    h = hashlib.sha256("\n".join(names).encode())
    h.update(np.ascontiguousarray(weights, dtype="<f8").tobytes())
    return h.hexdigest()[:32]


def _line(entry: dict) -> bytes:
    text = json.dumps(entry, separators=(",", ":"), allow_nan=False)
    return f"{zlib.crc32(text.encode()):08x} {text}\n".encode()


def _decode(raw: bytes) -> dict | None:
    if not raw.endswith(b"\n") or len(raw) < 10 or raw[8:9] != b" ":
        return None
    text = raw[9:-1]
    try:
        if int(raw[:8], 16) != zlib.crc32(text):
            return None
        entry = json.loads(text)
    except ValueError:
        return None
    return entry if isinstance(entry, dict) else None


class OtherSolve(ValueError):
    """The journal was written over another solve of the take."""


class EditJournal:
    """Open (and read back) the journal at ``path`` for the solve ``fp``.

    ``entries`` are the lines to replay; ``skipped`` counts the corrupt tail's lines."""

    def __init__(self, path: str | Path, fp: str) -> None:
        self.path = Path(path)
        self.entries: list[dict] = []
        self.skipped = 0
        good = 0
        if self.path.exists():
            lines = self.path.read_bytes().splitlines(keepends=True)
            head = _decode(lines[0]) if lines else None
            if lines and (head is None or head.get("magic") != MAGIC):
                raise ValueError(f"{self.path}: not a livecap review journal (or its header is corrupt)")
            if head is not None:
                if head.get("fingerprint") != fp:
                    raise OtherSolve(f"{self.path}: journal of another solve of this take (other --mode or "
                                     f"--weights); move it away to start afresh")
                good = len(lines[0])
                for i, raw in enumerate(lines[1:], start=1):
                    entry = _decode(raw)
                    if entry is None:
                        self.skipped = len(lines) - i
                        break
                    self.entries.append(entry)
                    good += len(raw)
        self.fh = open(self.path, "r+b" if self.path.exists() else "w+b")  # noqa: SIM115 (open for the session)
        try:
            fcntl.flock(self.fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self.fh.close()
            raise ValueError(f"{self.path}: in use by another livecap review of this take") from None
        self.fh.truncate(good)  # the corrupt tail goes before anything is appended
        self.fh.seek(good)
        if good == 0:
            self.append({"magic": MAGIC, "version": 1, "fingerprint": fp})
            _fsync_dir(self.path.parent)

    def append(self, entry: dict) -> None:
        self.fh.write(_line(entry))
        self.fh.flush()
        os.fsync(self.fh.fileno())

    def close(self) -> None:
        self.fh.close()


def open_journal(path: str | Path, fp: str) -> tuple[EditJournal, str | None]:
    """The journal at ``path`` for the solve ``fp``, and a one-line notice when one of another solve
    was set aside (renamed ``PATH.<UTC time>``) so that a fresh one could start."""
    path = Path(path)
    try:
        return EditJournal(path, fp), None
    except OtherSolve:
        aside = path.with_name(f"{path.name}.{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}")
        path.rename(aside)
        return EditJournal(path, fp), f"{path} held edits of another solve of this take: kept as {aside}"
