"""VRM expressions from ARKit weights, for VMC avatars without Perfect Sync clips.

VRM avatars carry a fixed set of expressions (VRM 1.0 ``expressions.preset``; VRM 0.x
``blendShapeMaster`` presets), not ARKit's 52 shapes. Each expression here is a weighted sum of
ARKit weights, clipped to [0, 1]; a term may be ``min(a,b)``, so ``blink`` is what both eyes share
and ``blinkLeft``/``blinkRight`` only the rest (VRM adds them, so a wink is not a half blink).
The table is data: ``livecap run --vrm-map FILE.json`` replaces it with the same structure
(expression -> {term: coefficient}), named by VRM 1.0 names. docs/protocol.md prints it.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from livecap.core.headpose import hamilton
from transport.arkit import ARKIT_NAMES, EYE_LOOK_INDEX, arkit_eye_angles

BLINK_BOTH = "min(eyeBlinkLeft,eyeBlinkRight)"

# VRM 1.0 preset -> {ARKit term: coefficient}; the visemes from the mouth shapes that make them.
VRM1_TABLE: dict[str, dict[str, float]] = {
    "aa": {"jawOpen": 1.0},
    "ih": {"mouthStretchLeft": 0.5, "mouthStretchRight": 0.5, "jawOpen": 0.2},
    "ou": {"mouthPucker": 1.0},
    "ee": {"mouthLowerDownLeft": 0.35, "mouthLowerDownRight": 0.35, "mouthUpperUpLeft": 0.15,
           "mouthUpperUpRight": 0.15, "jawOpen": 0.3},
    "oh": {"mouthFunnel": 1.0},
    "blink": {BLINK_BOTH: 1.0},
    "blinkLeft": {"eyeBlinkLeft": 1.0, BLINK_BOTH: -1.0},
    "blinkRight": {"eyeBlinkRight": 1.0, BLINK_BOTH: -1.0},
    "happy": {"mouthSmileLeft": 0.5, "mouthSmileRight": 0.5},
    "angry": {"browDownLeft": 0.5, "browDownRight": 0.5},
    "sad": {"mouthFrownLeft": 0.35, "mouthFrownRight": 0.35, "browInnerUp": 0.3},
    "relaxed": {"cheekSquintLeft": 0.5, "cheekSquintRight": 0.5},
    "surprised": {"eyeWideLeft": 0.35, "eyeWideRight": 0.35, "browInnerUp": 0.3},
}

# VRM 0.x preset name of each VRM 1.0 one (0.x has no "surprised").
VRM0_NAMES = {"aa": "A", "ih": "I", "ou": "U", "ee": "E", "oh": "O", "blink": "Blink", "blinkLeft": "Blink_L",
              "blinkRight": "Blink_R", "happy": "Joy", "angry": "Angry", "sad": "Sorrow", "relaxed": "Fun"}

_MIN = re.compile(r"^min\(\s*(\w+)\s*,\s*(\w+)\s*\)$")


def _index(name: str, where: str) -> int:
    if name not in ARKIT_NAMES:
        raise ValueError(f"{where}: {name!r} is not an ARKit blendshape name")
    return ARKIT_NAMES.index(name)


class VrmExpressions:
    """``expressions(arkit52) -> values``, one per name in ``names`` (VRM 0.x or 1.0 spelling)."""

    def __init__(self, version: int = 1, table: Mapping[str, Mapping[str, float]] | None = None,
                 where: str = "VRM table") -> None:
        if version not in (0, 1):
            raise ValueError(f"--vmc-vrm {version}: VRM version is 0 or 1")
        table = VRM1_TABLE if table is None else table
        keep = [e for e in table if version == 1 or e in VRM0_NAMES]
        self.names = [e if version == 1 else VRM0_NAMES[e] for e in keep]
        self._linear = np.zeros((len(keep), len(ARKIT_NAMES)))
        self._mins: list[tuple[int, int, int, float]] = []
        for row, expr in enumerate(keep):
            for term, coeff in table[expr].items():
                m = _MIN.match(term)
                if m:
                    self._mins.append((row, _index(m.group(1), where), _index(m.group(2), where), float(coeff)))
                else:
                    self._linear[row, _index(term, where)] += float(coeff)

    def __call__(self, arkit: np.ndarray) -> np.ndarray:
        out = self._linear @ arkit
        for row, a, b, coeff in self._mins:
            out[row] += coeff * min(arkit[a], arkit[b])
        return np.clip(out, 0.0, 1.0)


def load_vrm_table(path: str | Path) -> dict[str, dict[str, float]]:
    """A ``--vrm-map`` file: JSON object of VRM 1.0 expression -> {ARKit term: coefficient}."""
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{p}: cannot read VRM expression table ({exc})") from None
    ok = isinstance(data, dict) and all(
        isinstance(v, dict) and all(isinstance(c, int | float) for c in v.values()) for v in data.values())
    if not ok:
        raise ValueError(f"{p}: VRM table must be a JSON object of expression -> {{ARKit term: number}}")
    unknown = [e for e in data if e not in VRM1_TABLE]
    if unknown:
        raise ValueError(f"{p}: {unknown[0]!r} is not a VRM 1.0 expression preset")
    VrmExpressions(1, data, str(p))  # every term checked now, not at the first frame
    return data


def eye_rotations(arkit: np.ndarray, present: Sequence[bool]) -> tuple[np.ndarray, np.ndarray] | None:
    """LeftEye and RightEye local rotations (Unity quaternions x, y, z, w) from the eye-look shapes
    (livecap.core.eyes), or None when the rig has none of them. Unity: +yaw about +Y turns the eye
    to the avatar's right, +pitch about +X turns it down: the app's signs."""
    if not any(present[i] for i in EYE_LOOK_INDEX.ravel()):
        return None
    out = []
    for yaw, pitch in arkit_eye_angles(arkit):
        qy = np.array([0.0, np.sin(yaw / 2), 0.0, np.cos(yaw / 2)])
        qx = np.array([np.sin(pitch / 2), 0.0, 0.0, np.cos(pitch / 2)])
        out.append(hamilton(qy, qx))  # Unity's Euler order: yaw applied after pitch
    return out[0], out[1]
