"""Binary glTF 2.0 (.glb) of a blendshape rig: mesh with morph targets, optional keyed weights animation.

glTF 2.0 spec §3.7.2.2 (morph targets: POSITION deltas, mesh.weights defaults) and §3.11
(animations: a ``weights`` channel with one sampler for all targets; CUBICSPLINE output holds
in-tangent, value, out-tangent per key, tangents per second). Positions in metres (the spec's
unit; livecap's rigs are in mm). The linear part of the rig only: in-betweens and correctives have
no glTF equivalent.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from livecap.core.rig import Rig

MM = 0.001  # glTF units are metres
FLOAT, UINT = 5126, 5125


class _Builder:
    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, data: np.ndarray, kind: str, ctype: int = FLOAT, target: int | None = None,
            bounds: bool = False) -> int:
        raw = np.ascontiguousarray(data, dtype=np.float32 if ctype == FLOAT else np.uint32).tobytes()
        while len(self.blob) % 4:
            self.blob.append(0)
        view = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        self.blob += raw
        self.views.append(view)
        acc = {"bufferView": len(self.views) - 1, "componentType": ctype,
               "count": int(len(data) if kind != "SCALAR" else np.size(data)), "type": kind}
        if bounds:
            acc["min"] = np.asarray(data).min(0).astype(float).tolist()
            acc["max"] = np.asarray(data).max(0).astype(float).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def rig_glb(rig: Rig, names: list[str] | None = None, key_times: np.ndarray | None = None,
            values: np.ndarray | None = None, in_tangents: np.ndarray | None = None,
            out_tangents: np.ndarray | None = None) -> bytes:
    """The rig as .glb bytes; with ``key_times`` (K,) and K x m ``values``/tangents, a CUBICSPLINE
    morph-weights animation named "keys" (weights in the order of ``names``, default the rig's)."""
    names = list(names or rig.names)
    order = [rig.index(n) for n in names]
    b = _Builder()
    pos = b.add(rig.neutral * MM, "VEC3", target=34962, bounds=True)
    idx = b.add(rig.triangles.reshape(-1), "SCALAR", UINT, target=34963)
    targets = [{"POSITION": b.add(rig.deltas[j] * MM, "VEC3", target=34962, bounds=True)} for j in order]
    gltf: dict = {
        "asset": {"version": "2.0", "generator": "livecap"},
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "face"}],
        "meshes": [{"name": "face", "primitives": [{"attributes": {"POSITION": pos}, "indices": idx,
                                                    "targets": targets, "mode": 4}],
                    "weights": [0.0] * len(names), "extras": {"targetNames": names}}],
    }
    if key_times is not None:
        K, m = np.shape(values)
        if m != len(names) or len(key_times) != K:
            raise ValueError(f"glTF keys: {K} x {m} values for {len(key_times)} times and {len(names)} shapes")
        out = np.stack([in_tangents, values, out_tangents], axis=1).reshape(-1)  # per key: in, value, out
        t_acc = b.add(np.asarray(key_times, dtype=np.float64), "SCALAR", bounds=False)
        b.accessors[t_acc]["min"] = [float(np.min(key_times))]
        b.accessors[t_acc]["max"] = [float(np.max(key_times))]
        o_acc = b.add(out, "SCALAR")
        gltf["animations"] = [{"name": "keys", "samplers": [{"input": t_acc, "output": o_acc,
                                                            "interpolation": "CUBICSPLINE"}],
                               "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]}]
    while len(b.blob) % 4:
        b.blob.append(0)
    gltf["buffers"] = [{"byteLength": len(b.blob)}]
    gltf["bufferViews"], gltf["accessors"] = b.views, b.accessors
    js = json.dumps(gltf, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + len(b.blob)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON") + js
            + struct.pack("<I4s", len(b.blob), b"BIN\0") + bytes(b.blob))


def write_rig_glb(path: str | Path, rig: Rig, **keys) -> None:
    Path(path).write_bytes(rig_glb(rig, **keys))
