"""A solved take as glTF 2.0 binary (.glb): the rig's neutral mesh, one morph target per shape and one
animation carrying the weight curves and the head pose (Khronos glTF 2.0 §3.7.2.2 morph targets,
§3.11 animations).

Written through pygltflib (a plain, typed model of the glTF JSON with GLB packing) rather than
trimesh, whose exporter writes static meshes only: morph targets, ``targetNames`` and animation
channels have to be set on the JSON model anyway. glTF morph targets are linear, so a rig's
in-between and corrective shapes are not carried: each target is the shape's full delta.
Units are metres (the rig's millimetres / 1000), axes as the rig's (glTF expects +Y up).

Vertex normals are written (the base mesh's NORMAL and each target's NORMAL delta, §3.7.2.1 and
§3.7.2.2): without them Blender imports every polygon flat and three.js shades faceted. They are the
area-weighted average of the incident triangles' normals, so a target's normal delta is the normal of
the fully applied shape minus the neutral's (renderers add then renormalise).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib as g

from livecap.core.rig import Rig

_FLOAT = g.FLOAT
_UINT = g.UNSIGNED_INT


class Blob:
    """The GLB binary chunk, grown one 4-byte-aligned buffer view (with its accessor) at a time, after
    ``data`` (4-byte aligned) when given."""

    def __init__(self, doc: g.GLTF2, data: bytearray | None = None) -> None:
        self.doc = doc
        self.data = bytearray() if data is None else data

    def add(self, array: np.ndarray, kind: str, component: int, target: int | None = None,
            bounds: bool = False) -> int:
        raw = np.ascontiguousarray(array, dtype=np.uint32 if component == _UINT else np.float32)
        offset = len(self.data)
        self.data += raw.tobytes()
        self.data += b"\0" * (-len(self.data) % 4)
        self.doc.bufferViews.append(g.BufferView(buffer=0, byteOffset=offset, byteLength=raw.nbytes, target=target))
        flat = raw.reshape(raw.shape[0], -1)
        acc = g.Accessor(bufferView=len(self.doc.bufferViews) - 1, componentType=component, count=flat.shape[0],
                         type=kind)
        if bounds:
            acc.min = [float(v) for v in flat.min(axis=0)]
            acc.max = [float(v) for v in flat.max(axis=0)]
        self.doc.accessors.append(acc)
        return len(self.doc.accessors) - 1


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit area-weighted vertex normals (V x 3); a vertex in no triangle of non-zero area gets +Z so
    the NORMAL accessor stays unit length, as the spec requires."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    face = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])  # length = 2 x area
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, tri[:, k], face)
    length = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.divide(acc, length, out=np.zeros_like(acc), where=length > 0)
    out[length[:, 0] <= 0] = (0.0, 0.0, 1.0)
    return out


def _check(rig: Rig, names: list[str], times: np.ndarray, weights: np.ndarray,
           head_rotation: np.ndarray | None, head_translation: np.ndarray | None) -> np.ndarray:
    """The weights reordered to the rig's shapes (absent shapes stay 0); a clear error otherwise."""
    T = len(times)
    if weights.shape != (T, len(names)):
        raise ValueError(f"weights are {weights.shape}, expected {T} frames x {len(names)} shapes")
    if T < 1 or not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0) or times[0] < 0:
        raise ValueError("times must be finite, >= 0 and strictly increasing")
    unknown = [n for n in names if n not in rig.names]
    if unknown:
        raise ValueError(f"rig has no shape named {unknown[0]!r} ({len(unknown)} weight columns not in the rig)")
    for label, arr, width in (("head_rotation", head_rotation, 4), ("head_translation", head_translation, 3)):
        if arr is not None and np.shape(arr) != (T, width):
            raise ValueError(f"{label} must be {T} x {width}, got {np.shape(arr)}")
    out = np.zeros((T, rig.n_shapes))
    out[:, [rig.names.index(n) for n in names]] = np.nan_to_num(weights)
    return out


def glb_bytes(rig: Rig, names: list[str], times: np.ndarray, weights: np.ndarray,
              head_rotation: np.ndarray | None = None, head_translation: np.ndarray | None = None,
              name: str = "livecap take", tangents: tuple[np.ndarray, np.ndarray] | None = None) -> bytes:
    """The .glb of a solved take.

    ``tangents`` (in, out; each T x len(names), per second): the weights are keys of a CUBICSPLINE
    sampler (glTF 2.0 Appendix C: in-tangent, value, out-tangent per key) instead of LINEAR samples.

    ``times`` (T, seconds from the take's start), ``weights`` (T x len(names)), ``head_rotation``
    (T x 4 unit quaternions x, y, z, w) and ``head_translation`` (T x 3, metres) in the rig's axes,
    animating the one node that holds the mesh.
    """
    times = np.asarray(times, dtype=np.float64)
    w = _check(rig, list(names), times, np.asarray(weights, dtype=np.float64), head_rotation, head_translation)
    doc = g.GLTF2(asset=g.Asset(generator="livecap", version="2.0"), scene=0, scenes=[g.Scene(nodes=[0])],
                  buffers=[], bufferViews=[], accessors=[])
    blob = Blob(doc)
    positions = blob.add(rig.neutral / 1000.0, g.VEC3, _FLOAT, g.ARRAY_BUFFER, bounds=True)
    indices = blob.add(rig.triangles.reshape(-1), g.SCALAR, _UINT, g.ELEMENT_ARRAY_BUFFER)
    targets = [{"POSITION": blob.add(d / 1000.0, g.VEC3, _FLOAT, g.ARRAY_BUFFER, bounds=True)} for d in rig.deltas]
    normals = None
    if len(rig.triangles):  # a marker-only rig has no surface to shade
        base = vertex_normals(rig.neutral, rig.triangles)
        normals = blob.add(base, g.VEC3, _FLOAT, g.ARRAY_BUFFER)
        for target, d in zip(targets, rig.deltas, strict=True):
            target["NORMAL"] = blob.add(vertex_normals(rig.neutral + d, rig.triangles) - base, g.VEC3, _FLOAT,
                                        g.ARRAY_BUFFER)
    doc.meshes = [g.Mesh(name="face", weights=[0.0] * rig.n_shapes, extras={"targetNames": list(rig.names)},
                         primitives=[g.Primitive(attributes=g.Attributes(POSITION=positions, NORMAL=normals),
                                                 indices=indices, targets=targets, mode=g.TRIANGLES)])]
    doc.nodes = [g.Node(name="head", mesh=0)]

    time_acc = blob.add(times, g.SCALAR, _FLOAT, bounds=True)
    interpolation, out = g.ANIM_LINEAR, w
    if tangents is not None:
        ins, outs = (_check(rig, list(names), times, np.asarray(a, dtype=np.float64), None, None) for a in tangents)
        interpolation, out = g.ANIM_CUBICSPLINE, np.stack([ins, w, outs], axis=1)
    samplers = [g.AnimationSampler(input=time_acc, output=blob.add(out.reshape(-1), g.SCALAR, _FLOAT),
                                   interpolation=interpolation)]
    channels = [g.AnimationChannel(sampler=0, target=g.AnimationChannelTarget(node=0, path=g.WEIGHTS))]
    if head_rotation is not None:
        q = np.asarray(head_rotation, dtype=np.float64)
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        samplers.append(g.AnimationSampler(input=time_acc, output=blob.add(q, g.VEC4, _FLOAT),
                                           interpolation=g.ANIM_LINEAR))
        channels.append(g.AnimationChannel(sampler=len(samplers) - 1,
                                           target=g.AnimationChannelTarget(node=0, path=g.ROTATION)))
    if head_translation is not None:
        samplers.append(g.AnimationSampler(input=time_acc, output=blob.add(head_translation, g.VEC3, _FLOAT),
                                           interpolation=g.ANIM_LINEAR))
        channels.append(g.AnimationChannel(sampler=len(samplers) - 1,
                                           target=g.AnimationChannelTarget(node=0, path=g.TRANSLATION)))
    doc.animations = [g.Animation(name=name, samplers=samplers, channels=channels)]
    doc.buffers = [g.Buffer(byteLength=len(blob.data))]
    doc.set_binary_blob(bytes(blob.data))
    return b"".join(doc.save_to_bytes())


def write_glb(path: str | Path, rig: Rig, names: list[str], times: np.ndarray, weights: np.ndarray,
              head_rotation: np.ndarray | None = None, head_translation: np.ndarray | None = None) -> None:
    """Write :func:`glb_bytes` to ``path``."""
    Path(path).write_bytes(glb_bytes(rig, names, times, weights, head_rotation, head_translation,
                                     name=Path(path).stem))
