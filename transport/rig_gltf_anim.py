"""A solved take written back into the user's own glTF / GLB / VRM file: the file as it was (meshes,
materials, skins, the VRM extension) plus one animation of the face mesh's morph-target weights
(glTF 2.0 §3.11: a ``weights`` channel on the node that holds the mesh, LINEAR, one output value per
morph target per key, so targets the rig did not solve stay 0) and, from a solve's .glb, the head's
rotation on a VRM's humanoid head bone (turned about its joint from its rest pose).

The result is always a GLB container (what .vrm files are); a JSON .gltf's buffers are packed into its
binary chunk.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livecap.core.rig import RigError
from transport.rig_files import ImportedRig
from transport.rig_gltf import Reader, parse_gltf, target_names, world_matrices


def _pack(doc, buffers: list[bytes]) -> bytearray:
    """Every buffer in one blob (buffer 0, the GLB binary chunk), buffer views moved to match."""
    blob, base = bytearray(), []
    for data in buffers:
        base.append(len(blob))
        blob += data + b"\0" * (-len(data) % 4)
    for bv in doc.bufferViews or []:
        bv.byteOffset = (bv.byteOffset or 0) + base[bv.buffer]
        bv.buffer = 0
    return blob


def read_solved_glb(path: str | Path) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray | None]:
    """Shape names, times, weights (T x m) and head rotation (T x 4 quaternions x y z w, rig axes, relative to
    the neutral pose; None when absent) of the .glb ``livecap solve --out take.glb`` writes."""
    path = Path(path)
    doc, buffers = parse_gltf(path)
    reader = Reader(doc, buffers, path)
    if not doc.animations:
        raise RigError(f"{path}: no animation to read weights from")
    anim = doc.animations[0]
    weights = rotation = times = None
    names: list[str] = []
    for ch in anim.channels:
        sampler = anim.samplers[ch.sampler]
        times = reader.read(sampler.input)[:, 0]
        if ch.target.path == "weights":
            mesh = doc.meshes[doc.nodes[ch.target.node].mesh]
            names = target_names(mesh, max(len(p.targets or []) for p in mesh.primitives))
            weights = reader.read(sampler.output).reshape(len(times), -1)
        elif ch.target.path == "rotation":
            rotation = reader.read(sampler.output).reshape(len(times), 4)
    if weights is None or len(names) != weights.shape[1] or names[:1] == ["target0"]:
        raise RigError(f"{path}: no named morph-target weights animation (expected livecap solve's .glb)")
    return names, times, weights, rotation


def _head_bone(doc) -> int | None:
    """The node of a VRM's humanoid head bone (VRM 0.x list, VRM 1.0 mapping)."""
    ext = doc.extensions or {}
    if "VRMC_vrm" in ext:
        return ((ext["VRMC_vrm"].get("humanoid") or {}).get("humanBones") or {}).get("head", {}).get("node")
    if "VRM" in ext:
        bones = (ext["VRM"].get("humanoid") or {}).get("humanBones") or []
        return next((b.get("node") for b in bones if b.get("bone") == "head"), None)
    return None


def _head_keys(doc, node: int, rotation: np.ndarray, vrm0: bool) -> np.ndarray:
    """The head bone's local rotation keys that turn it by ``rotation`` (world, rig axes) about its joint from
    its rest pose: local = parent^-1 * R * parent * rest (VRM 0's -Z facing undone first)."""
    from scipy.spatial.transform import Rotation

    world = world_matrices(doc)
    parents = {c: i for i, n in enumerate(doc.nodes) for c in n.children or []}
    parent = world.get(parents.get(node), np.eye(4))[:3, :3]
    p = Rotation.from_matrix(parent / np.linalg.norm(parent, axis=0))
    rest = Rotation.from_quat(doc.nodes[node].rotation or [0.0, 0.0, 0.0, 1.0])
    q = np.asarray(rotation, dtype=np.float64)
    if vrm0:  # the rig's axes are VRM 0's turned 180 degrees about +Y
        q = q * np.array([-1.0, 1.0, -1.0, 1.0])
    return (p.inv() * Rotation.from_quat(q) * p * rest).as_quat()


def animate_gltf(source: str | Path, out: str | Path, imported: ImportedRig, names: list[str], times: np.ndarray,
                 weights: np.ndarray, animation: str = "livecap", head_rotation: np.ndarray | None = None) -> int:
    """Write ``source`` with an animation of ``weights`` (T x len(names), columns named by the rig's shapes or
    by the VRM expressions that drive one shape alone) to ``out``; returns the number of morph targets.
    ``head_rotation`` (T x 4, rig axes, relative to the neutral pose) turns a VRM's humanoid head bone."""
    import pygltflib as g

    from transport.gltf import Blob

    source, out = Path(source), Path(out)
    if imported.node is None:
        raise RigError(f"{source}: mesh {imported.mesh!r} is on no node of the scene: nothing to animate")
    times = np.asarray(times, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != (len(times), len(names)) or len(times) < 1:
        raise ValueError(f"weights are {weights.shape}, expected {len(times)} frames x {len(names)} shapes")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0) or times[0] < 0:
        raise ValueError("times must be finite, >= 0 and strictly increasing")
    if head_rotation is not None and np.shape(head_rotation) != (len(times), 4):
        raise ValueError(f"head rotation is {np.shape(head_rotation)}, expected {len(times)} x 4")
    shape = {n: k for k, n in enumerate(imported.rig.names)}
    for expr, binds in imported.expressions.items():  # columns of a rig imported with --names expressions
        if len(binds) == 1 and abs(next(iter(binds.values())) - 1.0) < 1e-6 and expr not in shape:
            shape[expr] = shape[next(iter(binds))]
    unknown = [n for n in names if n not in shape]
    if unknown:
        raise ValueError(f"{source}: mesh {imported.mesh!r} has no shape named {unknown[0]!r} "
                         f"({len(unknown)} weight columns not in the rig)")
    doc, buffers = parse_gltf(source)
    mesh = doc.meshes[doc.nodes[imported.node].mesh]
    n_targets = max(len(p.targets or []) for p in mesh.primitives)
    keys = np.zeros((len(times), n_targets), dtype=np.float32)
    for col, name in enumerate(names):
        keys[:, imported.targets[shape[name]]] = np.nan_to_num(weights[:, col])

    for acc in doc.accessors or []:
        if acc.bufferView is None:  # pygltflib reads an absent byteOffset as 0, which needs a bufferView
            acc.byteOffset = None
    blob = Blob(doc, _pack(doc, buffers))
    sampler = g.AnimationSampler(input=blob.add(times, g.SCALAR, g.FLOAT, bounds=True),
                                 output=blob.add(keys.reshape(-1), g.SCALAR, g.FLOAT), interpolation=g.ANIM_LINEAR)
    samplers = [sampler]
    channels = [g.AnimationChannel(sampler=0, target=g.AnimationChannelTarget(node=imported.node, path=g.WEIGHTS))]
    if head_rotation is not None:
        head = _head_bone(doc)
        if head is None:
            raise RigError(f"{source}: no VRM humanoid head bone to turn (the head rotation needs a VRM)")
        keys_q = _head_keys(doc, head, head_rotation, imported.format == "VRM 0.x")
        samplers.append(g.AnimationSampler(input=sampler.input, output=blob.add(keys_q, g.VEC4, g.FLOAT),
                                           interpolation=g.ANIM_LINEAR))
        channels.append(g.AnimationChannel(sampler=1, target=g.AnimationChannelTarget(node=head, path=g.ROTATION)))
    doc.animations = [*(doc.animations or []), g.Animation(name=animation, samplers=samplers, channels=channels)]
    doc.buffers = [g.Buffer(byteLength=len(blob.data))]
    doc.set_binary_blob(bytes(blob.data))
    out.write_bytes(b"".join(doc.save_to_bytes()))
    return n_targets
