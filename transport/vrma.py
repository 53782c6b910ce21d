"""A solve as a VRM Animation (.vrma, VRMC_vrm_animation 1.0): the animation alone, for VRM runtimes.

A VRM runtime (three-vrm, UniVRM) drives a face through its expressions and resets the morph targets they
bind every frame, so a plain morph-weights animation is lost there; a .vrma carries expression weights
instead. Per the VRMC_vrm_animation spec, each expression is a node whose translation x is its weight,
named in ``extensions.VRMC_vrm_animation.expressions`` (VRM 1.0 preset names, or custom names), and the
humanoid bones are nodes whose rotation tracks turn them (local, in a T-pose skeleton facing +Z).

Only expressions that drive one morph target alone at full weight carry a solved weight (one per target,
the one named like the target first, as ``rig import --names expressions`` chooses); the head's rotation
(rig axes, +Z out of the face, as VRM 1.0) goes on the humanoid head bone of a minimal hips -> head
skeleton whose rest rotations are identity.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livecap.core.names import name_key
from livecap.core.rig import RigError
from transport.rig_files import ImportedRig

# VRM 0.x presetName -> VRM 1.0 preset (what runtimes call them once loaded)
VRM0_PRESETS = {"a": "aa", "i": "ih", "u": "ou", "e": "ee", "o": "oh", "blink": "blink", "blink_l": "blinkLeft",
                "blink_r": "blinkRight", "joy": "happy", "angry": "angry", "sorrow": "sad", "fun": "relaxed",
                "lookup": "lookUp", "lookdown": "lookDown", "lookleft": "lookLeft", "lookright": "lookRight",
                "neutral": "neutral"}
VRM1_PRESETS = set(VRM0_PRESETS.values()) | {"surprised"}


def expression_columns(imported: ImportedRig, vrm0_presets: dict[str, str]) -> dict[str, int]:
    """VRMA expression name -> rig shape index, one expression per shape (see the module doc).
    ``vrm0_presets``: a VRM 0.x file's group name -> presetName, to name its presets as VRM 1.0 does."""
    by_shape: dict[str, list[str]] = {}
    for expr, binds in imported.expressions.items():
        if len(binds) == 1 and abs(next(iter(binds.values())) - 1.0) < 1e-6:
            by_shape.setdefault(next(iter(binds)), []).append(expr)
    out = {}
    for shape, exprs in by_shape.items():
        best = next((e for e in exprs if name_key(e) == name_key(shape)), exprs[0])
        preset = vrm0_presets.get(best, "unknown")
        out[VRM0_PRESETS.get(preset, best)] = imported.rig.index(shape)
    return out


def vrma_bytes(imported: ImportedRig, vrm0_presets: dict[str, str], names: list[str], times: np.ndarray,
               weights: np.ndarray, head_rotation: np.ndarray | None = None) -> tuple[bytes, int]:
    """The .vrma of weights (T x len(names), columns named by the rig's shapes) and an optional head rotation,
    and the number of expressions it keys."""
    import pygltflib as g

    from transport.gltf import Blob

    columns = expression_columns(imported, vrm0_presets)
    if not columns:
        raise RigError(f"mesh {imported.mesh!r}: no VRM expression drives one of its targets alone: a VRM "
                       "animation has nothing to carry")
    col = {n: i for i, n in enumerate(names)}
    for expr, binds in imported.expressions.items():  # columns of a rig imported with --names expressions
        if expr in col and len(binds) == 1:
            col.setdefault(next(iter(binds)), col[expr])
    keyed = {e: col[imported.rig.names[k]] for e, k in columns.items() if imported.rig.names[k] in col}
    times = np.asarray(times, dtype=np.float32)
    doc = g.GLTF2(asset=g.Asset(version="2.0", generator="livecap"), scene=0, scenes=[g.Scene(nodes=[0, 2])],
                  buffers=[], bufferViews=[], accessors=[], extensionsUsed=["VRMC_vrm_animation"])
    doc.nodes = [g.Node(name="hips", translation=[0.0, 1.0, 0.0], children=[1]),
                 g.Node(name="head", translation=[0.0, 0.5, 0.0]),
                 g.Node(name="expressions", children=list(range(3, 3 + len(keyed))))]
    doc.nodes += [g.Node(name=e) for e in keyed]
    blob = Blob(doc)
    time_acc = blob.add(times, g.SCALAR, g.FLOAT, bounds=True)
    samplers, channels = [], []
    for node, c in enumerate(keyed.values(), 3):
        xyz = np.zeros((len(times), 3))
        xyz[:, 0] = np.clip(np.nan_to_num(weights[:, c]), 0.0, 1.0)
        samplers.append(g.AnimationSampler(input=time_acc, output=blob.add(xyz, g.VEC3, g.FLOAT),
                                           interpolation=g.ANIM_LINEAR))
        channels.append(g.AnimationChannel(sampler=len(samplers) - 1,
                                           target=g.AnimationChannelTarget(node=node, path=g.TRANSLATION)))
    ext: dict = {"specVersion": "1.0",
                 "expressions": {"preset": {e: {"node": n} for n, e in enumerate(keyed, 3) if e in VRM1_PRESETS},
                                 "custom": {e: {"node": n} for n, e in enumerate(keyed, 3) if e not in VRM1_PRESETS}},
           "humanoid": {"humanBones": {"hips": {"node": 0}, "head": {"node": 1}}}}
    if head_rotation is not None:
        q = np.asarray(head_rotation, dtype=np.float64)
        samplers.append(g.AnimationSampler(input=time_acc, output=blob.add(q / np.linalg.norm(q, axis=1)[:, None],
                                                                           g.VEC4, g.FLOAT),
                                           interpolation=g.ANIM_LINEAR))
        channels.append(g.AnimationChannel(sampler=len(samplers) - 1,
                                           target=g.AnimationChannelTarget(node=1, path=g.ROTATION)))
    doc.extensions = {"VRMC_vrm_animation": ext}
    doc.animations = [g.Animation(name="livecap", samplers=samplers, channels=channels)]
    doc.buffers = [g.Buffer(byteLength=len(blob.data))]
    doc.set_binary_blob(bytes(blob.data))
    return b"".join(doc.save_to_bytes()), len(keyed)


def vrm0_preset_names(doc) -> dict[str, str]:
    """A VRM 0.x document's blend shape group name -> presetName (empty for VRM 1.0 and glTF)."""
    groups = (((doc.extensions or {}).get("VRM") or {}).get("blendShapeMaster") or {}).get("blendShapeGroups") or []
    return {g.get("name"): str(g.get("presetName", "unknown")).lower() for g in groups if g.get("name")}


def write_vrma(path: str | Path, source: str | Path, imported: ImportedRig, names: list[str], times: np.ndarray,
               weights: np.ndarray, head_rotation: np.ndarray | None = None) -> int:
    """Write the .vrma of a solve on ``source``'s rig to ``path``; returns the number of expressions keyed."""
    from transport.rig_gltf import parse_gltf

    doc, _ = parse_gltf(Path(source))
    data, n = vrma_bytes(imported, vrm0_preset_names(doc), names, times, weights, head_rotation)
    Path(path).write_bytes(data)
    return n
