"""Reader for the Live Link Face app's CSV (ARKit blendshape curves recorded on an iPhone).

Columns are mapped by header name, never by position (the app lists JawRight before JawLeft and
has spelt ``BlendShapeCount`` two ways). Rows ``timecode,0`` mean the face was lost; they are
dropped and the gap is left to the caller. Timecodes are ``HH:MM:SS:FF.mmm`` at 60 frames/s.
"""

from __future__ import annotations

import csv
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

    def resample(self, rate: float) -> tuple[np.ndarray, np.ndarray | None]:
        """Curves on a uniform grid at ``rate`` Hz, linear between rows (and across lost spans)."""
        t = np.arange(0.0, self.times[-1] + 1e-9, 1.0 / rate)
        w = np.stack([np.interp(t, self.times, c) for c in self.weights.T], 1)
        h = None if self.head is None else np.stack([np.interp(t, self.times, c) for c in self.head.T], 1)
        return w, h


def read_llf_csv(path: str | Path) -> ArkitCurves:
    """Read a Live Link Face CSV; a bad file raises one ValueError naming it."""
    p = Path(path)
    try:
        with open(p, newline="") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: cannot read Live Link Face CSV ({exc})") from None
    if not rows or not rows[0] or rows[0][0].strip().lower() != "timecode":
        raise ValueError(f"{p}: not a Live Link Face CSV (no Timecode header)")
    col = {name.strip().lower(): i for i, name in enumerate(rows[0])}
    shape_cols = [col.get(n.lower(), -1) for n in ARKIT_NAMES]
    if sum(c >= 0 for c in shape_cols) < 10:
        raise ValueError(f"{p}: fewer than 10 ARKit blendshape columns in the header")
    pose_cols = [col.get(n.lower(), -1) for n in POSE_NAMES[:3]]
    times, weights, head, lost = [], [], [], 0
    for k, row in enumerate(rows[1:], start=2):
        if len(row) < len(rows[0]):
            lost += 1
            continue
        try:
            times.append(parse_timecode(row[0], TIMECODE_RATE))
            weights.append([float(row[c]) if c >= 0 else 0.0 for c in shape_cols])
            head.append([float(row[c]) if c >= 0 else 0.0 for c in pose_cols])
        except ValueError:
            raise ValueError(f"{p}: line {k}: bad timecode or number") from None
    if len(times) < 2:
        raise ValueError(f"{p}: fewer than two tracked rows")
    t = np.asarray(times)
    t = np.where(t < t[0], t + 86400.0, t) - t[0]  # recording across midnight
    order = np.argsort(t, kind="stable")
    t, W, H = t[order], np.asarray(weights)[order], np.asarray(head)[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    H = H[keep]
    return ArkitCurves(t[keep], W[keep], H if np.abs(H).max() > 0 else None, lost)
