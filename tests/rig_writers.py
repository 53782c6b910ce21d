"""Third-party rig files for tests/test_rig_import*.py, written with pygltflib and pxr (not livecap's writer)
from an OBJ folder: GLB with a decoy body mesh, node transforms and sparse morph targets; VRM 0.x and 1.0
(GLB + the VRM extension's expression table, presets and Perfect Sync clips); USD with UsdSkel blend shapes.

Each file puts the rig's faces where the OBJ folder has them, in livecap's frame (+Y up, +Z out of the
face), once its format's conventions are undone (metres, node transforms, VRM 0's -Z facing, USD's
metersPerUnit and up axis), so an importer that reads it right gives back the OBJ folder's rig.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livecap.core.names import match_names
from livecap.core.objfile import read_obj
from transport.arkit import ARKIT_NAMES

PARENT_T = np.array([0.02, 0.05, -0.01])  # the face node's parent: a head bone, moved, turned 30 degrees, halved
PARENT_Q = np.array([0.0, np.sin(np.radians(15)), 0.0, np.cos(np.radians(15))])
PARENT_S = 0.5


@dataclass
class ObjRig:
    """An OBJ folder's faces in metres: neutral (V x 3), triangles, shape names and deltas (m x V x 3)."""

    neutral: np.ndarray
    triangles: np.ndarray
    names: list[str]
    deltas: np.ndarray


def read_obj_rig(folder: Path, names: list[str] | None, metres_per_unit: float) -> ObjRig:
    neutral, tris = read_obj(folder / "neutral.obj")
    names = names or sorted(p.stem for p in folder.glob("*.obj") if p.stem != "neutral")
    deltas = np.stack([read_obj(folder / f"{n}.obj")[0] - neutral for n in names])
    return ObjRig(neutral * metres_per_unit, tris, names, deltas * metres_per_unit)


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def perfect_sync_names(names: list[str]) -> dict[str, str]:
    """Perfect Sync clip name (ARKit, PascalCase) -> the rig's shape, for shapes that are one ARKit shape."""
    match = match_names(names, ARKIT_NAMES)
    return {a[0].upper() + a[1:]: names[s[0]] for a, s in zip(match.target, match.sources, strict=True)
            if len(s) == 1}


class _Blob:
    def __init__(self, doc) -> None:
        self.doc, self.data = doc, bytearray()

    def view(self, array: np.ndarray) -> int:
        import pygltflib as g

        raw = np.ascontiguousarray(array).tobytes()
        self.doc.bufferViews.append(g.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(raw)))
        self.data += raw + b"\0" * (-len(raw) % 4)
        return len(self.doc.bufferViews) - 1

    def accessor(self, array: np.ndarray, kind: str, bounds: bool = False) -> int:
        import pygltflib as g

        a = np.asarray(array, dtype=np.float32 if kind != g.SCALAR else np.uint32)
        acc = g.Accessor(bufferView=self.view(a), componentType=g.FLOAT if kind != g.SCALAR else g.UNSIGNED_INT,
                         count=len(a), type=kind)
        if bounds:
            acc.min, acc.max = a.min(0).tolist(), a.max(0).tolist()
        self.doc.accessors.append(acc)
        return len(self.doc.accessors) - 1

    def sparse_accessor(self, delta: np.ndarray) -> int:
        """A morph target as a sparse accessor without a base buffer view (zeros but the moved vertices)."""
        import pygltflib as g

        moved = np.flatnonzero(np.any(delta != 0, axis=1)).astype(np.uint32)
        vals = delta[moved].astype(np.float32)
        full = delta.astype(np.float32)
        acc = g.Accessor(componentType=g.FLOAT, count=len(delta), type=g.VEC3, byteOffset=None,
                         min=full.min(0).tolist(), max=full.max(0).tolist(),
                         sparse=g.Sparse(count=len(moved),
                                         indices=g.AccessorSparseIndices(bufferView=self.view(moved),
                                                                         componentType=g.UNSIGNED_INT),
                                         values=g.AccessorSparseValues(bufferView=self.view(vals))))
        self.doc.accessors.append(acc)
        return len(self.doc.accessors) - 1


def write_gltf(path: Path, rig: ObjRig, vrm: int | None = None, sparse: bool = False,
               parent: tuple = (PARENT_T, PARENT_Q, PARENT_S), as_matrix: bool = False, skinned: bool = False) -> Path:
    """A GLB (or .vrm when ``vrm`` is 0 or 1): scene root -> "Head" (``parent``: translation, rotation
    quaternion x y z w, uniform scale; as TRS or, ``as_matrix``, one column-major matrix) -> "Face" (the rig),
    a "Body" mesh without targets and a "Teeth" mesh with one target beside it.

    ``skinned``: the face is skinned instead, as exporters of characters write it: an "Armature" (turned,
    scale 0.01, so the mesh is stored in centimetres) with a head bone (bind matrix identity) and a jaw bone
    (an inverse bind matrix that puts it at the head's), each vertex 30 % head and 70 % jaw; the face's own
    node is moved, which glTF readers must ignore for a skinned mesh."""
    import pygltflib as g

    doc = g.GLTF2(asset=g.Asset(version="2.0", generator="livecap tests (pygltflib)"), scene=0,
                  buffers=[], bufferViews=[], accessors=[], meshes=[], nodes=[])
    blob = _Blob(doc)
    parent_t, parent_q, parent_s = (np.asarray(parent[0], float), np.asarray(parent[1], float), float(parent[2]))
    lin = _quat_matrix(parent_q) * parent_s
    world = rig.neutral.copy()
    deltas = rig.deltas
    if vrm == 0:  # VRM 0.x models face -Z
        world, deltas = world * [-1, 1, -1], deltas * [-1, 1, -1]
    if skinned:
        bones = _bones()
        lin, parent_t = bones["head"][:3, :3], bones["head"][:3, 3]
    inv = np.linalg.inv(lin)
    local = (world - parent_t) @ inv.T
    local_d = deltas @ inv.T
    targets = [{"POSITION": blob.sparse_accessor(d) if sparse else blob.accessor(d, g.VEC3, bounds=True)}
               for d in local_d]
    attributes = g.Attributes(POSITION=blob.accessor(local, g.VEC3, True))
    if skinned:
        n = len(local)
        attributes.JOINTS_0 = _joints(blob, np.tile(np.array([0, 1, 0, 0], np.uint8), (n, 1)))
        attributes.WEIGHTS_0 = blob.accessor(np.tile([0.3, 0.7, 0.0, 0.0], (n, 1)), g.VEC4)
    face = g.Mesh(name="Face", weights=[0.0] * len(rig.names), extras={"targetNames": list(rig.names)},
                  primitives=[g.Primitive(attributes=attributes,
                                          indices=blob.accessor(rig.triangles.reshape(-1), g.SCALAR),
                                          targets=targets)])
    box = np.array([[-0.2, 0, -0.1], [0.2, 0, -0.1], [0, 1.2, 0.1]])
    body = g.Mesh(name="Body", primitives=[g.Primitive(attributes=g.Attributes(
        POSITION=blob.accessor(box, g.VEC3, True)))])
    teeth = g.Mesh(name="Teeth", extras={"targetNames": ["jawOpen"]}, weights=[0.0], primitives=[g.Primitive(
        attributes=g.Attributes(POSITION=blob.accessor(box * 0.1, g.VEC3, True)),
        targets=[{"POSITION": blob.accessor(box * 0.01, g.VEC3, True)}])])
    doc.meshes = [body, teeth, face]
    doc.nodes = [g.Node(name="Root", children=[1, 2]), g.Node(name="Body", mesh=0),
                 g.Node(name="Head", children=[3, 4], **_transform(parent_t, parent_q, parent_s, as_matrix)),
                 g.Node(name="FaceNode", mesh=2), g.Node(name="TeethNode", mesh=1)]
    doc.scenes = [g.Scene(nodes=[0])]
    if skinned:
        doc.nodes += [g.Node(name="Armature", children=[6, 7], **bones["armature_trs"]),
                      g.Node(name="HeadBone", **bones["head_trs"]), g.Node(name="JawBone", **bones["jaw_trs"])]
        doc.nodes[0].children.append(5)
        ibm = np.stack([np.eye(4), np.linalg.inv(bones["jaw"]) @ bones["head"]])
        doc.skins = [g.Skin(joints=[6, 7], inverseBindMatrices=blob.accessor(
            ibm.transpose(0, 2, 1).reshape(2, 16), g.MAT4))]
        doc.nodes[3].skin = 0
        doc.nodes[3].translation = [5.0, 5.0, 5.0]
    if vrm is not None:
        _vrm_extension(doc, rig.names, vrm)
    doc.buffers = [g.Buffer(byteLength=len(blob.data))]
    doc.set_binary_blob(bytes(blob.data))
    path.write_bytes(b"".join(doc.save_to_bytes()))
    return path


def _bones() -> dict:
    """The skinned face's armature (turned 90 degrees about +X, scale 0.01) and its head and jaw bones."""
    def trs(t, q, s):
        m = np.eye(4)
        m[:3, :3] = _quat_matrix(np.asarray(q, float)) * s
        m[:3, 3] = t
        return m, {"translation": list(t), "rotation": list(q), "scale": [s] * 3}

    r = np.sqrt(0.5)
    arm, arm_trs = trs([0.0, 0.0, 0.0], [r, 0.0, 0.0, r], 0.01)
    head, head_trs = trs([0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 1.0], 1.0)
    jaw, jaw_trs = trs([0.0, -3.0, 4.0], [0.0, 0.0, np.sin(0.2), np.cos(0.2)], 1.0)
    return {"head": arm @ head, "jaw": arm @ jaw, "armature_trs": arm_trs, "head_trs": head_trs, "jaw_trs": jaw_trs}


def _joints(blob: _Blob, joints: np.ndarray) -> int:
    import pygltflib as g

    blob.doc.accessors.append(g.Accessor(bufferView=blob.view(joints), componentType=g.UNSIGNED_BYTE,
                                         count=len(joints), type=g.VEC4))
    return len(blob.doc.accessors) - 1


def _transform(t: np.ndarray, q: np.ndarray, scale: float, as_matrix: bool) -> dict:
    if not as_matrix:
        return {"translation": t.tolist(), "rotation": q.tolist(), "scale": [scale] * 3}
    m = np.eye(4)
    m[:3, :3] = _quat_matrix(q) * scale
    m[:3, 3] = t
    return {"matrix": m.T.ravel().tolist()}  # glTF matrices are column-major


BODY_BONES = ["hips", "spine", "leftUpperArm", "leftLowerArm", "leftHand", "rightUpperArm", "rightLowerArm",
              "rightHand", "leftUpperLeg", "leftLowerLeg", "leftFoot", "rightUpperLeg", "rightLowerLeg", "rightFoot"]


def _vrm_extension(doc, names: list[str], version: int) -> None:
    """Presets (A / aa = jawOpen; Blink / blink = both eye blinks) and one Perfect Sync clip per ARKit shape;
    the humanoid bones a VRM runtime requires (empty nodes under "Hips", the head bone "Head")."""
    import pygltflib as g

    index = {n: i for i, n in enumerate(names)}
    first = len(doc.nodes)
    doc.nodes += [g.Node(name=b, translation=[0.0, 0.05 * k, 0.0]) for k, b in enumerate(BODY_BONES)]
    doc.nodes[first].children = list(range(first + 1, len(doc.nodes)))
    doc.nodes[0].children.append(first)
    bones = {**{b: first + k for k, b in enumerate(BODY_BONES)}, "head": 2}
    presets = {"aa": ["jawOpen"], "blink": ["eyeBlink_L", "eyeBlink_R"]}
    clips = {k: [v] for k, v in perfect_sync_names(names).items()}
    if version == 0:
        vrm0 = {"aa": ("A", "a"), "blink": ("Blink", "blink")}
        groups = [{"name": vrm0[p][0], "presetName": vrm0[p][1], "isBinary": False,
                   "binds": [{"mesh": 2, "index": index[n], "weight": 100} for n in shapes if n in index]}
                  for p, shapes in presets.items()]
        groups += [{"name": c, "presetName": "unknown", "isBinary": False,
                    "binds": [{"mesh": 2, "index": index[s[0]], "weight": 100}]} for c, s in clips.items()]
        doc.extensionsUsed = ["VRM"]
        doc.extensions = {"VRM": {"exporterVersion": "livecap tests", "specVersion": "0.0",
                                  "meta": {"title": "test", "version": "1"},
                                  "humanoid": {"humanBones": [{"bone": b, "node": n} for b, n in bones.items()]},
                                  "blendShapeMaster": {"blendShapeGroups": groups}}}
        return

    def expr(shapes: list[str]) -> dict:
        return {"morphTargetBinds": [{"node": 3, "index": index[n], "weight": 1.0} for n in shapes if n in index]}

    doc.extensionsUsed = ["VRMC_vrm"]
    meta = {"name": "test", "authors": ["livecap tests"], "licenseUrl": "https://vrm.dev/licenses/1.0/"}
    doc.extensions = {"VRMC_vrm": {"specVersion": "1.0", "meta": meta,
                                   "humanoid": {"humanBones": {b: {"node": n} for b, n in bones.items()}},
                                   "expressions": {"preset": {p: expr(s) for p, s in presets.items()},
                                                   "custom": {c: expr(s) for c, s in clips.items()}}}}


def write_usd(path: Path, rig: ObjRig, meters_per_unit: float = 0.01, up: str = "Z") -> Path:
    """A UsdSkel stage: /Root/Head (Xform, translated) / Face (Mesh bound to a skeleton, one BlendShape per
    shape, sparse pointIndices for half of them) and a decoy /Root/Body mesh; ``up`` "Z" stores the face
    turned +90 degrees about X (Z-up) as Audio2Face and Maya-Z scenes do."""
    from pxr import Gf, Tf, Usd, UsdGeom, UsdSkel, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up == "Z" else UsdGeom.Tokens.y)
    root = UsdSkel.Root.Define(stage, "/Root")
    stage.SetDefaultPrim(root.GetPrim())
    head = UsdGeom.Xform.Define(stage, "/Root/Head")
    units = 1.0 / meters_per_unit
    shift = np.array([0.005, 0.02, 0.05]) * units
    head.AddTranslateOp().Set(Gf.Vec3d(*shift.tolist()))
    turn = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]) if up == "Z" else np.eye(3)  # +Y up -> +Z up
    pts = (rig.neutral * units) @ turn.T
    pts_local = pts - shift
    deltas = (rig.deltas * units) @ turn.T
    mesh = UsdGeom.Mesh.Define(stage, "/Root/Head/Face")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts_local.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(rig.triangles)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(rig.triangles.reshape(-1).tolist()))
    tokens, targets = [], []
    for k, (name, d) in enumerate(zip(rig.names, deltas, strict=True)):
        shape = UsdSkel.BlendShape.Define(stage, f"/Root/Head/Face/{Tf.MakeValidIdentifier(name)}")
        if k % 2:
            moved = np.flatnonzero(np.any(d != 0, axis=1))
            shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(d[moved].astype(np.float32)))
            shape.CreatePointIndicesAttr(Vt.IntArray(moved.tolist()))
        else:
            shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(d.astype(np.float32)))
        tokens.append(name)
        targets.append(shape.GetPath())
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateBlendShapesAttr(Vt.TokenArray(tokens))
    binding.CreateBlendShapeTargetsRel().SetTargets(targets)
    body = UsdGeom.Mesh.Define(stage, "/Root/Body")
    body.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 0), Gf.Vec3f(1, 0, 0), Gf.Vec3f(0, 1, 0)]))
    body.CreateFaceVertexCountsAttr(Vt.IntArray([3]))
    body.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2]))
    stage.GetRootLayer().Save()
    return path
