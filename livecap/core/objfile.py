"""Wavefront OBJ reading and writing: the form rigs leave Maya and Blender in."""

from __future__ import annotations

from pathlib import Path

import numpy as np


class ObjError(ValueError):
    """A file that cannot be read as a mesh; the message names the file."""


def read_obj(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Return (vertices V x 3 float64, triangles F x 3 int64); polygons are fan-triangulated."""
    path = Path(path)
    verts: list[list[float]] = []
    tris: list[tuple[int, int, int]] = []
    try:
        text = path.read_text(errors="strict")
    except (OSError, UnicodeDecodeError) as exc:
        raise ObjError(f"{path}: cannot read OBJ ({exc})") from exc
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
    v = np.asarray(verts, dtype=np.float64)
    f = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ObjError(f"{path}: face index out of range (file has {len(v)} vertices)")
    return v, f


def write_obj(path: str | Path, vertices: np.ndarray, triangles: np.ndarray, comment: str = "") -> None:
    path = Path(path)
    lines = [f"# {c}" for c in comment.splitlines()] if comment else []
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices, dtype=float)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(triangles, dtype=int)]
    path.write_text("\n".join(lines) + "\n")
