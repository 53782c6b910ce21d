"""Wavefront OBJ reading and writing: the form rigs leave Maya and Blender in."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np


class ObjError(ValueError):
    """A file that cannot be read as a mesh; the message names the file."""


def read_obj(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Return (vertices V x 3 float64, triangles F x 3 int64); polygons are fan-triangulated."""
    path = Path(path)
    try:
        text = path.read_text(errors="strict")
    except (OSError, UnicodeDecodeError) as exc:
        raise ObjError(f"{path}: cannot read OBJ ({exc})") from exc
    fast = _read_regular(text)
    v, f = fast if fast is not None else _read_lines(path, text)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ObjError(f"{path}: face index out of range (file has {len(v)} vertices)")
    return v, f


_VERTEX = re.compile(r"^v (.*)$", re.M)
_FACE = re.compile(r"^f (.*)$", re.M)
_SLASHES = re.compile(r"/\S*")
_INDEX = r"\d+(?:/\S*)?"


def _read_regular(text: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The common file (3 coordinates per vertex, faces of one size with positive indices) parsed by
    numpy in C: a rig of 54 OBJs loads several times faster than line by line (issue 18: rig loading
    was most of ``livecap solve`` on the ICT rig). None for anything else, which :func:`_read_lines`
    reads (and reports with its line number)."""
    vl = _VERTEX.findall(text)
    fl = _FACE.findall(text)
    if not vl:
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # numpy warns (then stops) at a token it cannot parse
            v = np.fromstring(" ".join(vl), sep=" ")
            if len(v) != 3 * len(vl):
                return None
            if not fl:
                return v.reshape(-1, 3), np.zeros((0, 3), dtype=np.int64)
            idx = np.fromstring(_SLASHES.sub("", " ".join(fl)), dtype=np.int64, sep=" ")
    except (ValueError, DeprecationWarning):
        return None
    size = len(idx) // len(fl)
    if size < 3 or size * len(fl) != len(idx) or idx.min() <= 0:
        return None
    if not all(f.count(" ") == size - 1 for f in fl):  # else a line of other size or spacing: the full check
        one_size = re.compile(rf"^f +{_INDEX}(?: +{_INDEX}){{{size - 1}}}[ \t]*$", re.M)
        if len(one_size.findall(text)) != len(fl):
            return None
    faces = idx.reshape(-1, size) - 1
    fan = [np.stack([faces[:, 0], faces[:, k], faces[:, k + 1]], axis=1) for k in range(1, size - 1)]
    return v.reshape(-1, 3), np.stack(fan, axis=1).reshape(-1, 3)


def _read_lines(path: Path, text: str) -> tuple[np.ndarray, np.ndarray]:
    verts: list[list[float]] = []
    tris: list[tuple[int, int, int]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        if line.startswith("v "):
            parts = line.split()
            if len(parts) < 4:
                raise ObjError(f"{path}:{lineno}: vertex with fewer than 3 coordinates")
            try:
                verts.append([float(parts[1]), float(parts[2]), float(parts[3])])
            except ValueError as exc:
                raise ObjError(f"{path}:{lineno}: bad vertex coordinate ({exc})") from exc
        elif line.startswith("f "):
            idx = []
            for tok in line.split()[1:]:
                try:
                    i = int(tok.split("/")[0])
                except ValueError as exc:
                    raise ObjError(f"{path}:{lineno}: bad face index {tok!r}") from exc
                idx.append(i - 1 if i > 0 else len(verts) + i)
            if len(idx) < 3:
                raise ObjError(f"{path}:{lineno}: face with fewer than 3 vertices")
            tris.extend((idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1))
    if not verts:
        raise ObjError(f"{path}: no vertices")
    return np.asarray(verts, dtype=np.float64), np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def write_obj(path: str | Path, vertices: np.ndarray, triangles: np.ndarray, comment: str = "") -> None:
    path = Path(path)
    lines = [f"# {c}" for c in comment.splitlines()] if comment else []
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices, dtype=float)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(triangles, dtype=int)]
    path.write_text("\n".join(lines) + "\n")
