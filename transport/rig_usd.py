"""Rigs from USD (Pixar's usd-core, ``pxr``): a mesh with UsdSkel blend shapes (UsdSkelBindingAPI
``skel:blendShapes`` naming the shapes, ``skel:blendShapeTargets`` pointing at UsdSkelBlendShape prims).

A BlendShape's ``offsets`` are deltas in the mesh's space, for every point or, with ``pointIndices``, for the
points listed (sparse); its in-betweens (``inbetweens:NAME`` with a weight strictly between 0 and 1) become
livecap in-betweens (Lewis §3.2), others are left out with a warning. Points are taken at the default time
through the mesh's local-to-world transform, scaled by the stage's ``metersPerUnit`` to millimetres, and a
Z-up stage (``upAxis``) is turned to livecap's +Y up. Polygons are fan-triangulated (left-handed
orientation flipped), as livecap's OBJ reader does.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from livecap.core.rig import INBETWEEN_SEP, Rig, RigError
from transport.rig_files import ImportedRig, choose_mesh

log = logging.getLogger(__name__)

_Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _open(path: Path):
    from pxr import Tf, Usd

    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:
        raise RigError(f"{path}: not a USD file ({str(exc).strip().splitlines()[-1]})") from None
    if stage is None:
        raise RigError(f"{path}: not a USD file")
    return stage


def _triangles(counts: np.ndarray, indices: np.ndarray, left_handed: bool) -> np.ndarray:
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris = [(indices[s], indices[s + j], indices[s + j + 1]) for s, c in zip(starts, counts, strict=True)
            for j in range(1, c - 1)]
    out = np.array(tris, dtype=np.int64).reshape(-1, 3)
    return out[:, ::-1] if left_handed else out


def read_usd_rig(path: str | Path, mesh: str | None = None) -> ImportedRig:
    """The rig of a USD stage's face mesh (see the module doc); ``mesh`` chooses by prim name or path.
    A malformed stage is one RigError naming the file."""
    from pxr import Tf

    path = Path(path)
    try:
        return _read(path, mesh)
    except RigError:
        raise
    except (Tf.ErrorException, IndexError, TypeError, ValueError) as exc:
        raise RigError(f"{path}: malformed USD rig ({type(exc).__name__}: {str(exc).strip()[:200]})") from None


def _read(path: Path, mesh: str | None) -> ImportedRig:
    from pxr import Usd, UsdGeom, UsdSkel

    stage = _open(path)
    prims = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and p.HasAPI(UsdSkel.BindingAPI)
             and UsdSkel.BindingAPI(p).GetBlendShapesAttr().Get()]
    names = [p.GetName() for p in prims]
    by_path = [i for i, p in enumerate(prims) if str(p.GetPath()) == mesh]
    k = by_path[0] if by_path else choose_mesh(path, names, mesh)
    prim = prims[k]
    geom = UsdGeom.Mesh(prim)
    time = Usd.TimeCode.Default()
    points = np.array(geom.GetPointsAttr().Get(time), dtype=np.float64).reshape(-1, 3)
    counts = np.array(geom.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    indices = np.array(geom.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    if indices.size and indices.max() >= len(points):
        raise RigError(f"{path}: mesh {prim.GetPath()}: face index past its {len(points)} points")
    triangles = _triangles(counts, indices, geom.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded)

    world = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), dtype=np.float64)
    lin, shift = world[:3, :3].T, world[3, :3]  # USD matrices act on row vectors: p' = p M
    mm = UsdGeom.GetStageMetersPerUnit(stage) * 1000.0
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z:
        lin, shift = _Z_UP_TO_Y_UP @ lin, _Z_UP_TO_Y_UP @ shift
    lin = lin * mm
    neutral = points @ lin.T + shift * mm

    binding = UsdSkel.BindingAPI(prim)
    shape_names = [str(n) for n in binding.GetBlendShapesAttr().Get()]
    targets = binding.GetBlendShapeTargetsRel().GetTargets()
    if len(targets) != len(shape_names):
        raise RigError(f"{path}: mesh {prim.GetPath()}: {len(shape_names)} blend shape names but "
                       f"{len(targets)} blend shape targets")
    faces: dict[str, np.ndarray] = {}
    for name, target in zip(shape_names, targets, strict=True):
        shape = UsdSkel.BlendShape(stage.GetPrimAtPath(target))
        if not shape:
            raise RigError(f"{path}: blend shape {name!r}: {target} is not a BlendShape prim")
        point_idx = shape.GetPointIndicesAttr().Get()
        faces[name] = neutral + _offsets(path, name, shape.GetOffsetsAttr().Get(), point_idx, len(points)) @ lin.T
        for ib in shape.GetInbetweens():
            w = ib.GetWeight()
            if w is None or not 0.0 < w < 1.0:
                log.warning("%s: in-between %s of %s at weight %s left out (livecap's lie strictly "
                            "between 0 and 1)", path, ib.GetAttr().GetName(), name, w)
                continue
            delta = _offsets(path, name, ib.GetOffsets(), point_idx, len(points))
            faces[f"{name}{INBETWEEN_SEP}{w:g}"] = neutral + delta @ lin.T
    try:
        rig = Rig.from_whole_face(neutral, triangles, faces)
        order = [rig.index(n) for n in shape_names]  # the file's order, as glTF's targets keep theirs
        new = {old: i for i, old in enumerate(order)}
        rig = Rig(rig.neutral, rig.triangles, shape_names, rig.deltas[order],
                  inbetweens=[replace(ib, shape=new[ib.shape]) for ib in rig.inbetweens])
    except RigError as exc:
        raise RigError(f"{path}: mesh {prim.GetPath()}: {exc}") from None
    return ImportedRig(rig, "USD", names[k], tuple(names), tuple(range(len(shape_names))))


def _offsets(path: Path, name: str, offsets, point_idx, n_points: int) -> np.ndarray:
    off = np.array(offsets if offsets is not None else [], dtype=np.float64).reshape(-1, 3)
    out = np.zeros((n_points, 3))
    if point_idx is not None and len(point_idx):
        idx = np.array(point_idx, dtype=np.int64)
        if len(idx) != len(off) or idx.max() >= n_points or idx.min() < 0:
            raise RigError(f"{path}: blend shape {name!r}: pointIndices do not match its offsets or the mesh")
        out[idx] = off
    elif len(off) == n_points:
        out = off
    elif len(off):
        raise RigError(f"{path}: blend shape {name!r}: {len(off)} offsets for a mesh of {n_points} points")
    return out
