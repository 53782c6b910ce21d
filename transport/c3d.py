"""C3D marker takes through ezc3d (the C3D standard, c3d.org).

Points with a negative residual or NaN coordinates are missing. POINT:UNITS is honoured.
The file header's frame count is checked against the data, since ezc3d quietly accepts
truncated files.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from livecap.core.take import Take
from livecap.core.units import to_mm
from transport.errors import TakeFileError


def read_c3d(path: str | Path) -> Take:
    path = Path(path)
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
    declared = _header_frame_count(path)
    if declared is not None and declared != points.shape[2]:
        raise TakeFileError(
            f"{path}: truncated C3D: header declares {declared} frames, the file holds {points.shape[2]}"
        )
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


def _header_frame_count(path: Path) -> int | None:
    """Frame count from the raw 512-byte header (words 4-5), or None when it is saturated."""
    with open(path, "rb") as fh:
        head = fh.read(512)
        fh.seek(512)
        par = fh.read(4)
    if len(head) < 512:
        raise TakeFileError(f"{path}: shorter than a C3D header")
    if head[1] != 0x50:
        raise TakeFileError(f"{path}: not a C3D file (header key is {head[1]:#x}, expected 0x50)")
    endian = ">" if len(par) == 4 and par[3] == 86 else "<"
    first, last = struct.unpack(endian + "HH", head[6:10])
    if last == 0xFFFF or last < first:
        return None
    return last - first + 1


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
