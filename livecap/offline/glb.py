"""A solved take as a .glb (glTF 2.0: the rig's mesh, morph targets, weight and head-pose animation)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livecap.core.headpose import NeutralPose
from livecap.core.rig import Rig
from livecap.offline.solve import SolvedTake


def write_solved_glb(path: str | Path, rig: Rig, solved: SolvedTake, neutral_frames: int) -> None:
    """The .glb of a solve; the head pose relative to its mean over the neutral window (first frames)."""
    from transport.gltf import write_glb  # pygltflib: imported by the solves that write a .glb
    neutral = NeutralPose.mean_of(solved.head_rotation[:neutral_frames], solved.head_translation[:neutral_frames])
    rotation, shift = neutral.relative(solved.head_rotation, solved.head_translation)
    times = np.arange(len(solved.weights)) / solved.rate
    write_glb(str(path), rig, solved.names, times, solved.weights, rotation, shift)
