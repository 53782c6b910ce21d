"""Rigs from glTF 2.0 / GLB and VRM 0.x / 1.0 files: one mesh's morph targets as the rig's shapes.

glTF 2.0 (Khronos spec §3.7.2.2): a mesh's primitives each carry POSITION morph targets (deltas, possibly
sparse accessors §3.6.2.3, possibly normalized integers under KHR_mesh_quantization); the names are in
``mesh.extras.targetNames`` (the convention three.js, Blender and UniVRM write). Positions are metres
(§3.4), so they are scaled to livecap's millimetres; the node's world transform is applied (positions by
the whole matrix, deltas by its linear part), or for a skinned mesh (whose node's transform §3.7.3 says to
ignore) the rest pose's linear blend skinning: each vertex by the weighted sum of its joints' world matrices
times their inverse bind matrices (deltas by its linear part). Every primitive of the mesh is merged into
one vertex array in file order (primitives that share a POSITION accessor share their vertices), and the
copies writers split vertices into at seams (equal in the neutral and every target) are welded back into
the first, so marker bindings by vertex index refer to the file's order of distinct vertices.

VRM: 0.x (``extensions.VRM.blendShapeMaster.blendShapeGroups``, binds of mesh + morph index, weight
0-100; the model faces -Z, so it is turned 180 degrees about +Y to livecap's +Z out of the face) and 1.0
(``extensions.VRMC_vrm.expressions`` preset and custom, binds of node + morph index, weight 0-1, faces
+Z). The expression table says which targets each preset or Perfect Sync clip moves; the mesh most
expressions bind is the face.
"""

from __future__ import annotations

import base64
import struct
from pathlib import Path

import numpy as np

from livecap.core.rig import Rig, RigError
from transport.rig_files import ImportedRig, choose_mesh

_DTYPES = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_UNSUPPORTED = {"KHR_draco_mesh_compression": "Draco-compressed", "EXT_meshopt_compression": "meshopt-compressed"}
_TRIANGLES, _STRIP, _FAN = 4, 5, 6


def parse_gltf(path: Path):
    """The document (pygltflib's model) and its buffers' bytes, from a GLB container or a JSON .gltf."""
    import pygltflib as g

    data = path.read_bytes()
    if data[:4] == b"glTF" and (len(data) < 12 or struct.unpack_from("<I", data, 8)[0] != len(data)):
        declared = struct.unpack_from("<I", data, 8)[0] if len(data) >= 12 else "?"
        raise RigError(f"{path}: truncated GLB (its header says {declared} bytes, the file has {len(data)})")
    try:
        if data[:4] == b"glTF":
            doc = g.GLTF2.load_from_bytes(data)
        else:
            doc = g.GLTF2.from_json(data.decode("utf-8"))
    except (ValueError, KeyError, TypeError, IndexError, AttributeError, UnicodeDecodeError, struct.error) as exc:
        raise RigError(f"{path}: not a glTF 2.0 file ({type(exc).__name__}: {exc})") from None
    for ext in doc.extensionsRequired or []:
        if ext in _UNSUPPORTED:
            raise RigError(f"{path}: {_UNSUPPORTED[ext]} meshes ({ext}) are not read; decompress first "
                           "(e.g. npx @gltf-transform/cli copy IN OUT)")
    buffers = []
    for i, buf in enumerate(doc.buffers or []):
        uri = buf.uri
        if uri is None:
            blob = doc.binary_blob()
            if blob is None:
                raise RigError(f"{path}: buffer {i} has no data")
            buffers.append(blob)
        elif uri.startswith("data:"):
            buffers.append(base64.b64decode(uri.split(",", 1)[1]))
        else:
            try:
                buffers.append((path.parent / uri).read_bytes())
            except OSError as exc:
                raise RigError(f"{path}: buffer {i}: cannot read {uri} ({exc})") from None
    return doc, buffers


class Reader:
    """Accessors as float64 arrays (normalized and sparse ones too)."""

    def __init__(self, doc, buffers: list[bytes], path: Path) -> None:
        self.doc, self.buffers, self.path = doc, buffers, path

    def _view(self, index: int, offset: int, dtype: np.dtype, width: int, count: int) -> np.ndarray:
        bv = self.doc.bufferViews[index]
        buf = self.buffers[bv.buffer]
        start = (bv.byteOffset or 0) + offset
        stride = bv.byteStride or dtype.itemsize * width
        end = start + stride * (count - 1) + dtype.itemsize * width if count else start
        if end > min(len(buf), (bv.byteOffset or 0) + bv.byteLength):
            raise RigError(f"{self.path}: buffer view {index} is shorter than its accessor")
        return np.ndarray((count, width), dtype=dtype, buffer=buf, offset=start, strides=(stride, dtype.itemsize))

    def read(self, index: int) -> np.ndarray:
        acc = self.doc.accessors[index]
        dtype = np.dtype(_DTYPES[acc.componentType])
        width = _WIDTH[acc.type]
        if acc.bufferView is None:
            out = np.zeros((acc.count, width))
        else:
            out = self._view(acc.bufferView, acc.byteOffset or 0, dtype, width, acc.count).astype(np.float64)
        if acc.sparse is not None and acc.sparse.count:
            sp = acc.sparse
            idx = self._view(sp.indices.bufferView, sp.indices.byteOffset or 0,
                             np.dtype(_DTYPES[sp.indices.componentType]), 1, sp.count)[:, 0].astype(np.int64)
            if idx.size and idx.max() >= acc.count:
                raise RigError(f"{self.path}: accessor {index}: sparse index past its {acc.count} elements")
            out[idx] = self._view(sp.values.bufferView, sp.values.byteOffset or 0, dtype, width, sp.count)
        if acc.normalized and dtype.kind in "iu":
            out = np.maximum(out / np.iinfo(dtype).max, -1.0)
        return out


def _node_matrix(node) -> np.ndarray:
    if node.matrix is not None and len(node.matrix) == 16:
        return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF matrices are column-major
    x, y, z, w = node.rotation or (0.0, 0.0, 0.0, 1.0)
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = r * np.array(node.scale or (1.0, 1.0, 1.0))
    m[:3, 3] = node.translation or (0.0, 0.0, 0.0)
    return m


def world_matrices(doc) -> dict[int, np.ndarray]:
    """World matrix of every node reachable from the scene (or from every root when there is none)."""
    nodes = doc.nodes or []
    if doc.scenes:
        roots = list(doc.scenes[doc.scene or 0].nodes or [])
    else:
        children = {c for n in nodes for c in (n.children or [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    out: dict[int, np.ndarray] = {}
    stack = [(i, np.eye(4)) for i in roots]
    while stack:
        i, parent = stack.pop()
        if i in out:
            continue
        out[i] = parent @ _node_matrix(nodes[i])
        stack.extend((c, out[i]) for c in nodes[i].children or [])
    return out


def _triangles(mode: int, idx: np.ndarray) -> np.ndarray:
    if mode == _TRIANGLES:
        return idx[: len(idx) // 3 * 3].reshape(-1, 3)
    if mode == _STRIP:
        tris = [(idx[i], idx[i + 1], idx[i + 2]) if i % 2 == 0 else (idx[i + 1], idx[i], idx[i + 2])
                for i in range(len(idx) - 2)]
    elif mode == _FAN:
        tris = [(idx[0], idx[i], idx[i + 1]) for i in range(1, len(idx) - 1)]
    else:
        return np.zeros((0, 3), dtype=np.int64)  # points and lines carry no faces
    return np.array(tris, dtype=np.int64).reshape(-1, 3)


def _vrm_expressions(doc, node_mesh: dict[int, int]) -> tuple[str, dict[str, list[tuple[int, int, float]]]]:
    """(format, expression -> [(mesh, target, weight 0-1)]) of a VRM file, ("glTF", {}) otherwise."""
    ext = doc.extensions or {}
    table: dict[str, list[tuple[int, int, float]]] = {}
    if "VRMC_vrm" in ext:
        exprs = (ext["VRMC_vrm"] or {}).get("expressions") or {}
        for group in ("preset", "custom"):
            for name, e in (exprs.get(group) or {}).items():
                binds = [(node_mesh.get(b.get("node", -1), -1), int(b.get("index", -1)), float(b.get("weight", 1.0)))
                         for b in (e or {}).get("morphTargetBinds") or []]
                table[name] = [b for b in binds if b[0] >= 0]
        return "VRM 1.0", table
    if "VRM" in ext:
        groups = ((ext["VRM"] or {}).get("blendShapeMaster") or {}).get("blendShapeGroups") or []
        for grp in groups:
            name = grp.get("name") or grp.get("presetName") or ""
            if name:
                table[name] = [(int(b.get("mesh", -1)), int(b.get("index", -1)), float(b.get("weight", 100.0)) / 100)
                               for b in grp.get("binds") or []]
        return "VRM 0.x", table
    return "glTF", {}


def read_gltf_rig(path: str | Path, mesh: str | None = None) -> ImportedRig:
    """The rig of a glTF / GLB / VRM file (see the module doc); ``mesh`` chooses among several meshes.
    A malformed file (indices past its arrays, wrong types, truncated data) is one RigError naming it."""
    path = Path(path)
    try:
        return _read(path, mesh)
    except RigError:
        raise
    except (IndexError, KeyError, TypeError, AttributeError, ValueError, struct.error) as exc:
        raise RigError(f"{path}: malformed glTF ({type(exc).__name__}: {exc})") from None


def _read(path: Path, mesh: str | None) -> ImportedRig:
    doc, buffers = parse_gltf(path)
    reader = Reader(doc, buffers, path)
    meshes = doc.meshes or []
    with_targets = [i for i, m in enumerate(meshes) if any(p.targets for p in m.primitives or [])]
    nodes = doc.nodes or []
    node_mesh = {i: n.mesh for i, n in enumerate(nodes) if n.mesh is not None}
    fmt, table = _vrm_expressions(doc, node_mesh)
    names = [meshes[i].name or _node_name(nodes, i) or f"mesh{i}" for i in with_targets]
    bound = [b[0] for binds in table.values() for b in binds if b[0] in with_targets]
    preferred = names[with_targets.index(max(set(bound), key=bound.count))] if bound else None
    k = choose_mesh(path, names, mesh, preferred)
    mesh_index = with_targets[k]
    world = world_matrices(doc)
    users = [i for i in sorted(world) if nodes[i].mesh == mesh_index]
    node = users[0] if users else None
    skin = None if node is None or nodes[node].skin is None else _skin_matrices(reader, doc, world, nodes[node].skin)
    neutral, triangles, deltas = _weld(*_mesh_geometry(reader, meshes[mesh_index], path, skin))
    m = np.eye(4) if node is None or skin is not None else world[node]
    if fmt == "VRM 0.x":
        m = np.diag([-1.0, 1.0, -1.0, 1.0]) @ m
    neutral = (neutral @ m[:3, :3].T + m[:3, 3]) * 1000.0
    deltas = deltas @ m[:3, :3].T * 1000.0

    shape_names = target_names(meshes[mesh_index], len(deltas))
    try:
        rig = Rig(neutral, triangles, shape_names, deltas)
    except RigError as exc:
        raise RigError(f"{path}: mesh {names[k]!r}: {exc}") from None
    expressions = {e: {shape_names[t]: w for mi, t, w in binds if mi == mesh_index and 0 <= t < len(shape_names)}
                   for e, binds in table.items()}
    return ImportedRig(rig, fmt, names[k], tuple(names), tuple(range(len(shape_names))),
                       {e: b for e, b in expressions.items() if b}, node)


def _weld(neutral: np.ndarray, triangles: np.ndarray, deltas: np.ndarray):
    """One vertex for the copies glTF writers split a vertex into (UV seams, flat shading, Blender's
    exporter): equal in the neutral and in every target. The others keep the file's order (first copy)."""
    key = np.concatenate([neutral, deltas.transpose(1, 0, 2).reshape(len(neutral), -1)], axis=1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    if len(first) == len(neutral):
        return neutral, triangles, deltas
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    tris = rank[inverse.reshape(-1)][triangles]
    tris = tris[(tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])]
    keep = first[order]
    return neutral[keep], tris, deltas[:, keep]


def _node_name(nodes, mesh_index: int) -> str | None:
    return next((n.name for n in nodes if n.mesh == mesh_index and n.name), None)


def target_names(mesh, count: int) -> list[str]:
    for extras in [mesh.extras] + [p.extras for p in mesh.primitives or []]:
        names = (extras or {}).get("targetNames") if isinstance(extras, dict) else None
        if isinstance(names, list) and len(names) == count:
            return [str(n) for n in names]
    return [f"target{i}" for i in range(count)]


def _skin_matrices(reader: Reader, doc, world: dict[int, np.ndarray], index: int) -> np.ndarray:
    """Each joint's world matrix times its inverse bind matrix (glTF §3.7.3.3): the rest pose's skinning."""
    skin = doc.skins[index]
    joints = skin.joints or []
    if skin.inverseBindMatrices is None:
        ibm = np.tile(np.eye(4), (len(joints), 1, 1))
    else:
        ibm = reader.read(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
    if len(ibm) < len(joints):
        raise RigError(f"{reader.path}: skin {index} has fewer inverse bind matrices than joints")
    return np.stack([world.get(j, np.eye(4)) @ ibm[i] for i, j in enumerate(joints)]).reshape(-1, 4, 4)


def _skinned(reader: Reader, prim, skin: np.ndarray, pos: np.ndarray, deltas: np.ndarray):
    """Positions and deltas of a skinned primitive at the rest pose: linear blend of its joints' matrices."""
    attrs = prim.attributes
    if attrs.JOINTS_0 is None or attrs.WEIGHTS_0 is None:
        return pos, deltas
    joints = reader.read(attrs.JOINTS_0).astype(np.int64)
    weights = reader.read(attrs.WEIGHTS_0)
    if joints.size and joints.max() >= len(skin):
        raise RigError(f"{reader.path}: a vertex names joint {joints.max()} of a skin with {len(skin)}")
    total = weights.sum(axis=1, keepdims=True)
    weights = np.divide(weights, total, out=np.full_like(weights, 0.25), where=total > 0)
    per_vertex = np.einsum("vk,vkij->vij", weights, skin[joints])
    moved = np.einsum("vij,vj->vi", per_vertex[:, :3, :3], pos) + per_vertex[:, :3, 3]
    return moved, np.einsum("vij,mvj->mvi", per_vertex[:, :3, :3], deltas)


def _mesh_geometry(reader: Reader, mesh, path: Path,
                   skin: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merged neutral (V x 3), triangles and deltas (m x V x 3) of a mesh's primitives: in file units, or
    skinned at the rest pose by ``skin`` (joint matrices) for primitives with JOINTS_0 / WEIGHTS_0."""
    prims = mesh.primitives or []
    n_targets = max(len(p.targets or []) for p in prims)
    offsets: dict[int, int] = {}
    positions, deltas, tris = [], [], []
    count = 0
    for p in prims:
        pos_acc = p.attributes.POSITION
        if pos_acc is None:
            continue
        if pos_acc not in offsets:
            offsets[pos_acc] = count
            pos = reader.read(pos_acc)
            d = np.zeros((n_targets, len(pos), 3))
            for t, target in enumerate(p.targets or []):
                acc = target.get("POSITION") if isinstance(target, dict) else getattr(target, "POSITION", None)
                if acc is not None:
                    delta = reader.read(acc)
                    if delta.shape != pos.shape:
                        raise RigError(f"{path}: mesh {mesh.name!r}: morph target {t} has {len(delta)} vertices, "
                                       f"its primitive {len(pos)}")
                    d[t] = delta
            if skin is not None:
                pos, d = _skinned(reader, p, skin, pos, d)
            positions.append(pos)
            deltas.append(d)
            count += len(pos)
        n = len(positions[list(offsets).index(pos_acc)])
        idx = reader.read(p.indices)[:, 0].astype(np.int64) if p.indices is not None else np.arange(n)
        if idx.size and idx.max() >= n:
            raise RigError(f"{path}: mesh {mesh.name!r}: index past the primitive's {n} vertices")
        tris.append(_triangles(p.mode if p.mode is not None else _TRIANGLES, idx) + offsets[pos_acc])
    if not positions:
        raise RigError(f"{path}: mesh {mesh.name!r} has no POSITION attribute")
    return (np.concatenate(positions), np.concatenate(tris) if tris else np.zeros((0, 3), np.int64),
            np.concatenate(deltas, axis=1))

