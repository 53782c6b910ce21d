"""Reader for the Live Link Face app's CSV (ARKit blendshape curves recorded on an iPhone).

Columns are mapped by header name, never by position (the app lists JawRight before JawLeft and
has spelt ``BlendShapeCount`` two ways). Rows ``timecode,0`` mean the face was lost; they are
dropped, counted in ``lost``, and the gap is left to the caller. A row the app could not have
written (cut short, a number or timecode that does not parse, NaN) is skipped and counted in
``bad``: one damaged line does not cost the take. Timecodes are ``HH:MM:SS:FF.mmm`` at 60
frames/s, the phone's time of day; ``start`` keeps the first row's, so a take solved from the
file carries the app's timecode.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from transport.arkit import ARKIT_NAMES, POSE_NAMES
from transport.recorders import parse_timecode

TIMECODE_RATE = 60.0


@dataclass
class ArkitCurves:
    times: np.ndarray  # R seconds from the first row, increasing
    weights: np.ndarray  # R x 52 in ARKIT_NAMES order
    head: np.ndarray | None  # R x 3 yaw, pitch, roll (radians), None when the file has none (all zero)
    lost: int  # rows where tracking was lost (dropped)
    eyes: np.ndarray | None = None  # R x 6 left eye yaw, pitch, roll, right eye (radians); None when all zero
    start: float = 0.0  # the first row's timecode, seconds of the day
    bad: int = 0  # rows that do not parse (skipped)
    first_bad: str = ""  # where the first of them is, for the report

    @property
    def first_frame(self) -> int:
        """The first row's timecode as a frame number of the day at the timecode's 60 fps."""
        return int(round(self.start * TIMECODE_RATE))

    def resample(self, rate: float) -> tuple[np.ndarray, np.ndarray | None]:
        """Curves on a uniform grid at ``rate`` Hz, linear between rows (and across lost spans)."""
        w, h, _ = self.resample_all(rate)
        return w, h

    def resample_all(self, rate: float) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Weights, head and eye angles on a uniform grid at ``rate`` Hz from the first row."""
        t = np.arange(0.0, self.times[-1] + 1e-9, 1.0 / rate)

        def grid(x: np.ndarray | None) -> np.ndarray | None:
            return None if x is None else np.stack([np.interp(t, self.times, c) for c in x.T], 1)
        return grid(self.weights), grid(self.head), grid(self.eyes)


def is_llf_csv(path: str | Path) -> bool:
    """True when the file's first header cell is ``Timecode`` (the app's layout), without reading the rest."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            first = fh.readline(4096)
    except (OSError, UnicodeDecodeError):
        return False
    return first.split(",", 1)[0].strip().lower() == "timecode"


def read_llf_csv(path: str | Path) -> ArkitCurves:
    """Read a Live Link Face CSV; a bad file raises one ValueError naming it."""
    p = Path(path)
    try:
        with open(p, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ValueError(f"{p}: cannot read Live Link Face CSV ({exc})") from None
    if not rows or not rows[0] or rows[0][0].strip().lower() != "timecode":
        raise ValueError(f"{p}: not a Live Link Face CSV (no Timecode header)")
    col = {name.strip().lower(): i for i, name in enumerate(rows[0])}
    shape_cols = [col.get(n.lower(), -1) for n in ARKIT_NAMES]
    if sum(c >= 0 for c in shape_cols) < 10:
        raise ValueError(f"{p}: fewer than 10 ARKit blendshape columns in the header")
    pose_cols = [col.get(n.lower(), -1) for n in POSE_NAMES]
    times, weights, pose, lost, bad, first_bad = [], [], [], 0, 0, ""
    for k, row in enumerate(rows[1:], start=2):
        if len(row) == 2 and row[1].strip() == "0":
            lost += 1
            continue
        try:
            if len(row) < len(rows[0]):
                raise ValueError(f"{len(row)} of {len(rows[0])} cells")
            t = parse_timecode(row[0], TIMECODE_RATE)
            w = [float(row[c]) if c >= 0 else 0.0 for c in shape_cols]
            a = [float(row[c]) if c >= 0 else 0.0 for c in pose_cols]
            if not all(map(math.isfinite, [t, *w, *a])):
                raise ValueError("NaN or infinite value")
        except ValueError as exc:
            bad += 1
            first_bad = first_bad or f"line {k}: {exc}"
            continue
        times.append(t)
        weights.append(w)
        pose.append(a)
    if len(times) < 2:
        more = f"; {bad} unreadable rows, first {first_bad}" if bad else ""
        raise ValueError(f"{p}: fewer than two tracked rows{more}")
    t = np.asarray(times)
    start = float(t[0])
    t = np.where(t < t[0], t + 86400.0, t) - t[0]  # recording across midnight
    order = np.argsort(t, kind="stable")
    t, W, A = t[order], np.asarray(weights)[order], np.asarray(pose)[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    H, E = A[keep, :3], A[keep, 3:]
    return ArkitCurves(t[keep], W[keep], H if np.abs(H).max() > 0 else None, lost,
                       E if np.abs(E).max() > 0 else None, start, bad, first_bad)
