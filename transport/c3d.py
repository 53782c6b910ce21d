"""C3D marker takes through ezc3d (the C3D standard, c3d.org).

Points with a negative residual or NaN coordinates are missing. POINT:UNITS is honoured.
The header and parameter section are checked against the file's size first
(transport/c3d_check.py), since ezc3d trusts their counts: a flipped byte made it allocate
gigabytes or crash, and it quietly accepts truncated files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livecap.core.take import Take
from livecap.core.units import to_mm
from transport.c3d_check import check_c3d
from transport.errors import TakeFileError


def read_c3d(path: str | Path) -> Take:
    path = Path(path)
    layout = check_c3d(path)
    import ezc3d

    try:  # ezc3d's own c3d object, without the wrapper's copies of analogs, rotations and camera masks
        c = ezc3d.ezc3d.c3d(str(path))
    except Exception as exc:  # ezc3d raises plain RuntimeError/IOError with terse text
        raise TakeFileError(f"{path}: not a readable C3D file ({exc})") from None
    params = ezc3d.c3d.Parameters(c.parameters())["POINT"]
    points = c.get_points()
    n = points.shape[1]
    if n == 0:
        raise TakeFileError(f"{path}: C3D file holds no 3D marker points (analog or rotation data only)")
    if points.shape[2] < layout.frames:
        raise TakeFileError(f"{path}: truncated C3D: header declares {layout.frames} frames, the file holds "
                            f"{points.shape[2]}")
    labels = [str(s).strip() for s in params["LABELS"]["value"]][:n]
    labels += [f"M{i:03d}" for i in range(len(labels), n)]
    units_param = params.get("UNITS", {}).get("value", [])
    units = str(units_param[0]).strip() if len(units_param) else "mm"
    try:
        scale = to_mm(1.0, units or "mm")
    except ValueError as exc:
        raise TakeFileError(f"{path}: POINT:UNITS {exc}") from None
    rate = float(params["RATE"]["value"][0])
    if not (np.isfinite(rate) and rate > 0):
        raise TakeFileError(f"{path}: POINT:RATE is {rate}, not a frame rate")
    xyz = np.transpose(points[:3], (2, 1, 0)) * scale
    residuals = c.get_point_residuals()[0].T
    valid = np.isfinite(xyz).all(axis=2) & (residuals >= 0)
    first = int(c.header().firstFrame())
    return Take(labels, xyz, valid, rate, first)


def write_c3d(take: Take, path: str | Path) -> None:
    """Write marker positions in millimetres, missing markers with residual -1."""
    import ezc3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(take.rate)]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(take.labels)
    c.add_parameter("POINT", "UNITS", "mm")
    pts = np.ones((4, take.n_markers, take.n_frames))
    pts[:3] = np.transpose(take.positions, (2, 1, 0))
    c["data"]["points"] = pts
    res = np.where(take.valid.T, 0.0, -1.0)[None]
    c["data"]["meta_points"]["residuals"] = res
    c.write(str(path))
