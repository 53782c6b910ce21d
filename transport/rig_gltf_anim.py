"""A solved take written back into the user's own glTF / GLB / VRM file: the file as it was (meshes,
materials, skins, the VRM extension) plus one animation of the face mesh's morph-target weights
(glTF 2.0 §3.11: a ``weights`` channel on the node that holds the mesh, LINEAR, one output value per
morph target per key, so targets the rig did not solve stay 0).

The result is always a GLB container (what .vrm files are); a JSON .gltf's buffers are packed into its
binary chunk.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livecap.core.rig import RigError
from transport.rig_files import ImportedRig
from transport.rig_gltf import parse_gltf


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


def animate_gltf(source: str | Path, out: str | Path, imported: ImportedRig, names: list[str], times: np.ndarray,
                 weights: np.ndarray, animation: str = "livecap") -> int:
    """Write ``source`` with an animation of ``weights`` (T x len(names), columns named by the rig's shapes or
    by the VRM expressions that drive one shape alone) to ``out``; returns the number of morph targets."""
    import pygltflib as g

    source, out = Path(source), Path(out)
    if imported.node is None:
        raise RigError(f"{source}: mesh {imported.mesh!r} is on no node of the scene: nothing to animate")
    times = np.asarray(times, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != (len(times), len(names)) or len(times) < 1:
        raise ValueError(f"weights are {weights.shape}, expected {len(times)} frames x {len(names)} shapes")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0) or times[0] < 0:
        raise ValueError("times must be finite, >= 0 and strictly increasing")
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
    blob = _pack(doc, buffers)

    def accessor(array: np.ndarray, kind: str, bounds: bool) -> int:
        raw = np.ascontiguousarray(array, dtype=np.float32)
        blob.extend(b"\0" * (-len(blob) % 4))
        doc.bufferViews.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=raw.nbytes))
        blob.extend(raw.tobytes())
        acc = g.Accessor(bufferView=len(doc.bufferViews) - 1, componentType=g.FLOAT, count=len(raw), type=kind)
        if bounds:
            acc.min, acc.max = [float(raw.min())], [float(raw.max())]
        doc.accessors.append(acc)
        return len(doc.accessors) - 1

    sampler = g.AnimationSampler(input=accessor(times, g.SCALAR, True), output=accessor(keys.reshape(-1), g.SCALAR,
                                                                                        False),
                                 interpolation=g.ANIM_LINEAR)
    channel = g.AnimationChannel(sampler=0, target=g.AnimationChannelTarget(node=imported.node, path=g.WEIGHTS))
    doc.animations = [*(doc.animations or []), g.Animation(name=animation, samplers=[sampler], channels=[channel])]
    blob.extend(b"\0" * (-len(blob) % 4))
    doc.buffers = [g.Buffer(byteLength=len(blob))]
    doc.set_binary_blob(bytes(blob))
    out.write_bytes(b"".join(doc.save_to_bytes()))
    return n_targets
