"""Recorders: weights to CSV / JSONL, and the raw incoming markers, so a live session can be
edited afterwards and replayed exactly.

Durability contract: rows are written as they come and pushed to the operating system by
:meth:`flush` (the pipeline calls it every few hundred milliseconds and at exit); ``flushed``
counts the frames pushed so far. Data the OS holds survives ``kill -9`` of the process (and,
with ``fsync=True``, a power cut), so every frame counted in ``flushed`` is readable. Readers
ignore a torn last line.

* CSV: ``frame,time,<shape>...`` (what ``livecap solve`` writes), or, when the rig's names are
  ARKit names, the Live Link Face app's CSV, byte for byte as the app writes it:
  ``Timecode,BlendShapeCount,EyeBlinkLeft,...,RightEyeRoll``, ``\n`` line ends, time-of-day
  ``HH:MM:SS:FF.mmm`` timecodes with FF 00-59 (60 fps, whatever the stream's rate), values with
  ten fixed decimals, head angles relative to the neutral head pose.
* JSONL: a header line ``{"type": "header", "names": [...]}`` then one object per frame.
* Markers: ``.npz`` (labels, frames, timestamps, positions, valid, rate) or ``.c3d``. Both are
  whole-file formats, so frames go first to an append-only journal ``<path>.partial`` (a JSON
  header line, then fixed-size binary records) that becomes the final file on close;
  :func:`read_marker_journal` recovers a session that was killed. Journal version 2 ends the
  header and every record with a CRC32 (zlib), so a damaged record is dropped and counted, never
  recovered as markers metres off; version 1 journals (no checksums) are still read, unverified.
"""

from __future__ import annotations

import csv
import glob
import json
import math
import os
import struct
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np

from livecap.core.headpose import NeutralWindow
from livecap.core.take import MarkerFrame, Take
from livecap.core.timecode import TimecodeClock, format_timecode
from transport.arkit import ARKIT_NAMES, POSE_NAMES, arkit_eye_angles, arkit_matrix, head_angles, is_arkit
from transport.wire import WIRE_VERSION, layout_id

# Column order of the Live Link Face app's CSV (it lists jaw and mouth Right before Left).
LLF_CSV_SHAPES = [n[0].upper() + n[1:] for n in ARKIT_NAMES]
for _a, _b in (("JawLeft", "JawRight"), ("MouthLeft", "MouthRight")):
    _i, _j = LLF_CSV_SHAPES.index(_a), LLF_CSV_SHAPES.index(_b)
    LLF_CSV_SHAPES[_i], LLF_CSV_SHAPES[_j] = LLF_CSV_SHAPES[_j], LLF_CSV_SHAPES[_i]
LLF_CSV_HEADER = ["Timecode", "BlendShapeCount", *LLF_CSV_SHAPES, *POSE_NAMES]


class _Appending:
    """An append-only file with explicit flush accounting: ``flushed`` frames survive kill -9."""

    fh: IO
    fsync: bool = False
    written = 0  # frames handed to the file object
    flushed = 0  # frames handed to the operating system

    def flush(self) -> None:
        if self.fh.closed:
            return
        self.fh.flush()
        if self.fsync:
            os.fsync(self.fh.fileno())
        self.flushed = self.written


class _Lines(_Appending):
    """An append-only text file."""

    def __init__(self, path: str | Path, fsync: bool = False) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fh = open(self.path, "w", newline="", buffering=1 << 16)
        self.fsync = fsync

    def close(self) -> None:
        if not self.fh.closed:
            self.flush()
            self.fh.close()

    def stats(self) -> dict:
        return {"written": self.written, "flushed": self.flushed}


def timecode(seconds: float, rate: float) -> str:
    """Live Link Face CSV timecode ``HH:MM:SS:FF.mmm`` (FF frames at ``rate``, mmm sub-frame)."""
    fps = max(1, int(round(rate)))
    total = seconds * fps
    whole = math.floor(total + 1e-9)
    sub = min(int(round((total - whole) * 1000)), 999)
    ff = whole % fps
    s = whole // fps
    return f"{s // 3600:02d}:{s // 60 % 60:02d}:{s % 60:02d}:{ff:02d}.{sub:03d}"


LLF_CSV_FPS = 60  # the app's CSV timecode counts frames 00-59


def _fixed(v: float) -> str:
    """Ten fixed decimals, as the app writes; never ``-0.0000000000``."""
    return f"{round(v, 10) + 0.0:.10f}"


def parse_timecode(tc: str, rate: float) -> float:
    h, m, s, f = tc.split(":")
    return int(h) * 3600 + int(m) * 60 + int(s) + float(f) / max(1, int(round(rate)))


class CsvRecorder(_Lines):
    """Weights CSV; ``layout`` is ``auto`` (Live Link Face layout when every shape name is an
    ARKit name), ``livecap`` or ``livelinkface``. In the Live Link Face layout a stream faster than
    the 60 fps timecode (120 Hz markers) keeps the first result of each timecode frame, as the
    app writes at most one row per frame; the others are counted in ``merged``."""

    def __init__(self, path: str | Path, rate: float = 60.0, layout: str = "auto", mapping: dict | None = None,
                 fsync: bool = False, timecode: str = "clock", neutral_frames: int = 1) -> None:
        if layout not in ("auto", "livecap", "livelinkface"):
            raise ValueError(f"unknown CSV layout {layout!r}")
        super().__init__(path, fsync)
        self.rate = rate
        self.layout = layout
        self.mapping = mapping
        self._writer = csv.writer(self.fh)
        self.clock = TimecodeClock(timecode, rate)
        self.neutral = NeutralWindow(neutral_frames)
        self._names = None
        self._M: np.ndarray | None = None
        self._last_frame = ""
        self.merged = 0  # results in a timecode frame that already has its row (Live Link Face layout)

    def _start(self, names) -> None:
        if self._names is not None:
            raise ValueError(f"{self.path}: shape names changed during a recording")
        self._names = names
        if self.layout == "livelinkface" or (self.layout == "auto" and is_arkit(names)):
            self.layout = "livelinkface"
            M = arkit_matrix(names, self.mapping, str(self.path))
            order = [ARKIT_NAMES.index(n[0].lower() + n[1:]) for n in LLF_CSV_SHAPES]
            self._M = M[order]
            self._to_arkit = np.argsort(order)  # the CSV's (app's) shape order back to ARKit's
            self._writer = csv.writer(self.fh, lineterminator="\n")
            self._writer.writerow(LLF_CSV_HEADER)
        else:
            self.layout = "livecap"
            self._writer.writerow(["frame", "time", *names])

    def stats(self) -> dict:
        return {**super().stats(), "merged": self.merged}

    def publish(self, result) -> None:
        if result.names is not self._names:
            self._start(result.names)
        w = np.asarray(result.weights, dtype=float)
        if self._M is not None:
            pose = np.zeros(9)
            pose[:3] = head_angles(self.neutral.relative(result.head_rotation, result.head_translation)[0])
            arkit = self._M @ w
            pose[[3, 4, 6, 7]] = arkit_eye_angles(arkit[self._to_arkit]).ravel()
            tc = format_timecode(self.clock.seconds_of_day(result.timestamp, result.received), LLF_CSV_FPS)
            if tc[:11] == self._last_frame:  # the app writes at most one row per timecode frame: the first
                self.merged += 1
                return
            self._last_frame = tc[:11]
            row = [tc, 61, *map(_fixed, arkit.tolist()), *map(_fixed, pose.tolist())]
        else:
            row = [int(result.frame), repr(float(result.timestamp)), *map(repr, w.tolist())]
        self._writer.writerow(row)
        self.written += 1


@dataclass
class WeightsRecording:
    names: list[str]
    frames: np.ndarray  # T (for the Live Link Face layout: round(time * rate))
    times: np.ndarray  # T seconds (Live Link Face layout: from its first row's timecode)
    weights: np.ndarray  # T x m
    layout: str


def read_csv_recording(path: str | Path, rate: float = 60.0) -> WeightsRecording:
    """Read either CSV layout back; a torn last line (a killed writer) is ignored."""
    path = Path(path)
    text = path.read_text()
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    rows = [r for r in csv.reader(text.splitlines()) if r]
    if not rows:
        raise ValueError(f"{path}: empty recording")
    header = rows[0]
    try:
        data = np.array([[float(c) for c in r[1:]] for r in rows[1:]], dtype=float).reshape(len(rows) - 1, -1)
        if header[:2] == ["frame", "time"]:
            frames = np.array([int(r[0]) for r in rows[1:]])
            return WeightsRecording(header[2:], frames, data[:, 0], data[:, 1:], "livecap")
        if header[:2] == ["Timecode", "BlendShapeCount"]:
            of_day = np.array([parse_timecode(r[0], LLF_CSV_FPS) for r in rows[1:]])
            times = (of_day - of_day[:1]) % 86400.0 if len(of_day) else of_day
            return WeightsRecording(header[2:], np.round(times * rate).astype(int), times, data[:, 1:],
                                    "livelinkface")
    except ValueError as exc:
        raise ValueError(f"{path}: bad recording row ({exc})") from None
    raise ValueError(f"{path}: not a weights recording (header starts {header[:2]})")


class JsonlRecorder(_Lines):
    def __init__(self, path: str | Path, fsync: bool = False) -> None:
        super().__init__(path, fsync)
        self._names = None

    def publish(self, result) -> None:
        """One row with the keys of the ZeroMQ weights message (docs/protocol.md §3), as JSON."""
        if result.names is not self._names:
            self._names = result.names
            self._names_id = layout_id(result.names)
            self.fh.write(json.dumps({"type": "header", "version": WIRE_VERSION, "names": list(result.names),
                                      "names_id": self._names_id}) + "\n")
        row = {
            "v": WIRE_VERSION, "type": "weights", "frame": int(result.frame), "timestamp": float(result.timestamp),
            "names_id": self._names_id, "weights": np.asarray(result.weights, dtype=float).tolist(),
            "head_rotation": np.asarray(result.head_rotation, dtype=float).tolist(),
            "head_translation": np.asarray(result.head_translation, dtype=float).tolist(),
            "residual": float(result.residual), "solve_time": float(result.solve_time),
        }
        if result.valid is not None:
            row["markers"], row["valid"] = int(len(result.valid)), int(np.count_nonzero(result.valid))
        if result.at_bound is not None:
            row["at_bound"] = np.asarray(result.at_bound, dtype=int).tolist()
        self.fh.write(json.dumps(row) + "\n")
        self.written += 1


def read_jsonl_recording(path: str | Path) -> tuple[list[str], list[dict]]:
    """Shape names and the per-frame objects; a torn last line is ignored."""
    names: list[str] = []
    frames: list[dict] = []
    with open(path) as fh:
        for line in fh:
            if not line.endswith("\n"):
                break
            obj = json.loads(line)
            if obj.get("type") == "header":
                names = obj["names"]
            else:
                frames.append(obj)
    return names, frames


# ------------------------------------------------------------------------------ raw markers
_JOURNAL_MAGIC = "livecap-markers"


class MarkerRecorder(_Appending):
    """Record every accepted input frame (session label order) to ``.npz`` or ``.c3d``."""

    def __init__(self, path: str | Path, labels: list[str], rate: float, fsync: bool = False) -> None:
        self.path = Path(path)
        if self.path.suffix.lower() not in (".npz", ".c3d"):
            raise ValueError(f"{self.path}: raw marker recordings are .npz or .c3d")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.labels = list(labels)
        self.rate = float(rate)
        self.fsync = fsync
        self.journal = journal_path(self.path)
        remove_stale_temporaries(self.path)
        n = len(self.labels)
        self._fmt = f"<qd{3 * n}d{n}B"  # float64: a replay reproduces the session bit for bit
        self.fh = open(self.journal, "wb", buffering=1 << 16)
        head = {"magic": _JOURNAL_MAGIC, "version": 2, "labels": self.labels, "rate": self.rate, "record": self._fmt}
        self.fh.write((json.dumps({**head, "crc32": _crc(head)}) + "\n").encode())

    def record(self, frame: MarkerFrame) -> None:
        rec = struct.pack(self._fmt, int(frame.frame), float(frame.timestamp),
                          *np.asarray(frame.positions, dtype=np.float64).ravel(),
                          *np.asarray(frame.valid, dtype=np.uint8))
        self.fh.write(rec + struct.pack("<I", zlib.crc32(rec)))
        self.written += 1

    def close(self) -> None:
        if self.fh.closed:
            return
        self.flush()
        os.fsync(self.fh.fileno())  # the journal is the only copy until the final file is renamed in
        self.fh.close()
        rec = read_marker_journal(self.journal)
        write_marker_recording(rec, self.path)
        self.journal.unlink()

    def stats(self) -> dict:
        return {"written": self.written, "flushed": self.flushed}


def journal_path(path: str | Path) -> Path:
    p = Path(path)
    return p.with_name(p.name + ".partial")


def _crc(head: dict) -> int:
    return zlib.crc32(json.dumps(head).encode())


@dataclass
class MarkerRecording:
    take: Take  # positions in mm, session label order
    frames: np.ndarray  # T frame numbers as received
    timestamps: np.ndarray  # T seconds as received
    dropped: list[int] | None = None  # journal records (0-based) whose checksum failed; None: not verified
    torn: int = 0  # bytes of a last record cut short (a kill mid-write)

    def journal_report(self) -> str:
        """What recovery kept and left out, for ``livecap recover`` to say."""
        if self.dropped is None:
            note = "version 1 journal: no checksums, records not verified"
        elif self.dropped:
            shown = ", ".join(map(str, self.dropped[:10])) + (" ..." if len(self.dropped) > 10 else "")
            note = f"dropped {len(self.dropped)} damaged records (CRC32 mismatch; records {shown})"
        else:
            note = "every record's checksum verified"
        return note + (f"; ignored a torn last record ({self.torn} bytes)" if self.torn else "")


def read_marker_journal(path: str | Path) -> MarkerRecording:
    """Recover the frames of a journal: complete records whose checksum holds (version 2), or every
    complete record (version 1, which has none)."""
    path = Path(path)
    with open(path, "rb") as fh:
        head_line = fh.readline(1 << 24)
        body = fh.read()
    try:
        head = json.loads(head_line)
        if not isinstance(head, dict) or head.get("magic") != _JOURNAL_MAGIC:
            raise ValueError("wrong magic")
        version = head.get("version")
        if version not in (1, 2):
            raise ValueError(f"version {version!r}")
        if version == 2 and head.pop("crc32", None) != _crc(head):
            raise ValueError("its header fails its checksum")
        fmt = head["record"]
        labels, rate = [str(s) for s in head["labels"]], float(head["rate"])
        size = struct.calcsize(fmt)
    except (ValueError, KeyError, TypeError, struct.error) as exc:
        raise ValueError(f"{path}: not a livecap marker journal ({exc})") from None
    n = len(labels)
    fields = [("frame", "<i8"), ("t", "<f8"), ("pos", "<f8", (n, 3)), ("valid", "u1", (n,))]
    if np.dtype(fields).itemsize != size:
        raise ValueError(f"{path}: record format {fmt!r} is not one this build writes")
    if version == 2:
        fields.append(("crc", "<u4"))
    rec = np.dtype(fields)
    count = len(body) // rec.itemsize
    arr = np.frombuffer(body[: count * rec.itemsize], dtype=rec)
    dropped = None
    if version == 2:
        raw = np.frombuffer(body[: count * rec.itemsize], np.uint8).reshape(count, rec.itemsize)
        good = np.array([zlib.crc32(r[:size]) == c for r, c in zip(raw, arr["crc"], strict=True)], dtype=bool)
        dropped = np.flatnonzero(~good).tolist()
        arr = arr[good]
    take = Take(labels, arr["pos"].astype(np.float64), arr["valid"].astype(bool), rate,
                int(arr["frame"][0]) if len(arr) else 0)
    return MarkerRecording(take, arr["frame"].copy(), arr["t"].copy(), dropped, len(body) - count * rec.itemsize)


def write_marker_recording(rec: MarkerRecording, path: str | Path) -> None:
    """Write the whole recording atomically: to a temporary name beside ``path``, fsync, rename,
    fsync the folder. A kill at any point leaves either no final file or a complete one."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        if path.suffix.lower() == ".c3d":
            from transport.c3d import write_c3d

            write_c3d(rec.take, tmp)
        else:
            with open(tmp, "wb") as fh:  # np.savez would append .npz to a name without it
                np.savez_compressed(fh, labels=np.array(rec.take.labels), frames=rec.frames,
                                    timestamps=rec.timestamps, positions=rec.take.positions, valid=rec.take.valid,
                                    rate=np.array(rec.take.rate))
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    _fsync_dir(path.parent)


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Remove the ``.NAME.PID.tmp.EXT`` files :func:`write_marker_recording` leaves when killed
    mid-write, for this target only and only when that PID is no longer running."""
    path = Path(path)
    removed = []
    for tmp in path.parent.glob(f".{glob.escape(path.stem)}.*.tmp{glob.escape(path.suffix)}"):
        pid = tmp.name[len(path.stem) + 2: -len(".tmp" + path.suffix)]
        if pid.isdigit() and not _running(int(pid)):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True  # someone else's process (or a number no process has): leave its file
    return True


def recover_marker_journal(journal: str | Path, out: str | Path | None = None) -> tuple[Path, int]:
    """Turn the journal a killed session left into its final recording; returns (path, frames).
    The journal stays until the final file is safely in place."""
    path, rec = recover_marker_journal_report(journal, out)
    return path, rec.take.n_frames


def recover_marker_journal_report(journal: str | Path, out: str | Path | None = None
                                  ) -> tuple[Path, MarkerRecording]:
    """:func:`recover_marker_journal` with the recording, whose ``journal_report()`` says what was dropped."""
    journal = Path(journal)
    if not journal.name.endswith(".partial"):
        raise ValueError(f"{journal}: not a journal (expected a name ending in .partial)")
    if not journal.exists():
        raise ValueError(f"{journal}: no such file")
    out = Path(out) if out else journal.with_name(journal.name[: -len(".partial")])
    if out.suffix.lower() not in (".npz", ".c3d"):
        raise ValueError(f"{out}: raw marker recordings are .npz or .c3d")
    rec = read_marker_journal(journal)
    if rec.take.n_frames == 0:
        raise ValueError(f"{journal}: holds no complete frame ({rec.journal_report()})")
    remove_stale_temporaries(out)
    write_marker_recording(rec, out)
    return out, rec


def read_marker_recording(path: str | Path) -> MarkerRecording:
    """A raw ``.npz`` marker recording, or a ``.partial`` journal left by a killed session."""
    path = Path(path)
    if path.name.endswith(".partial"):
        return read_marker_journal(path)
    try:
        _check_npz_sizes(path)
        z = np.load(path, allow_pickle=False)
        labels = [str(s) for s in z["labels"]]
        take = Take(labels, z["positions"].astype(np.float64), z["valid"], float(z["rate"]),
                    int(z["frames"][0]) if len(z["frames"]) else 0)
        return MarkerRecording(take, z["frames"], z["timestamps"])
    except (OSError, KeyError, ValueError, IndexError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: not a livecap marker recording ({exc})") from None


DEFLATE_MAX_RATIO = 1032  # deflate cannot expand a byte to more than ~1032 (zlib's technical notes)


def _check_npz_sizes(path: Path) -> None:
    """numpy allocates what an array's header declares before reading its data: a 1 kB archive
    claiming a (100000, 10000, 3) array cost 22 GiB. Every member's declared size must fit the size
    the archive records for it (which zipfile holds the data to)."""
    from numpy.lib import format as npy

    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            with zf.open(info) as fh:
                version = npy.read_magic(fh)
                read = {(1, 0): npy.read_array_header_1_0, (2, 0): npy.read_array_header_2_0}.get(version)
                if read is None:
                    raise ValueError(f"{info.filename} is .npy version {version}")
                shape, _, dtype = read(fh)
                need = math.prod(shape) * dtype.itemsize
                if need > info.file_size or need > DEFLATE_MAX_RATIO * info.compress_size + 4096:
                    raise ValueError(f"{info.filename} declares {shape} {dtype} ({need} bytes), the archive holds "
                                     f"{info.file_size} ({info.compress_size} compressed)")
