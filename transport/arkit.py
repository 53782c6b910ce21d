"""ARKit blendshape names and the mapping from any rig's shape names onto them.

Unreal's Live Link Face, VTuber "perfect sync" avatars and the Live Link Face CSV all speak
Apple's 52 ARKit blendshapes (ARFaceAnchor.BlendShapeLocation). A rig with other names (ICT
FaceKit's ``eyeBlink_L``, a studio's own) is mapped automatically where the names agree up to
case, separators and the side suffix (``_L``/``_R``/``Left``/``Right``; ``livecap.core.names``, the
matcher every name mapping uses); an ARKit shape that
exists only per side in the rig (ICT's ``browInnerUp_L`` / ``_R`` for ``browInnerUp``) takes
the mean of the sides. A JSON mapping file overrides or completes the automatic match.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from livecap.core.eyes import LOOKS, eye_angles, eye_yaw_pitch
from livecap.core.names import ARKIT_NAMES, arkit_matrix, is_arkit

__all__ = ["ARKIT_NAMES", "arkit_matrix", "is_arkit"]  # the names below livecap.core; wire formats import them here

# The nine rotations after the 52 shapes in a Live Link Face packet / CSV row.
POSE_NAMES = ["HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
              "RightEyeYaw", "RightEyePitch", "RightEyeRoll"]

EYE_LOOK_INDEX = np.array([[ARKIT_NAMES.index(f"eyeLook{look}{side}") for look in LOOKS]
                           for side in ("Left", "Right")])
_EYE_LOOKS = EYE_LOOK_INDEX.ravel().tolist()


def arkit_eye_angles(arkit: np.ndarray) -> np.ndarray:
    """Eye (yaw, pitch) of the left and right eye (2 x 2, radians) from 52 ARKit weights."""
    return eye_angles(np.asarray(arkit, dtype=float)[EYE_LOOK_INDEX])


def arkit_eye_yaw_pitch(arkit: list[float]) -> tuple[float, ...]:
    """:func:`arkit_eye_angles` of 52 Python floats, flat (left yaw, pitch, right yaw, pitch): a per-packet path."""
    return eye_yaw_pitch([arkit[i] for i in _EYE_LOOKS])


def load_mapping(path: str | Path) -> dict:
    """A mapping file: JSON object ``{"<ARKit name>": "<rig shape>" | ["<rig shape>", ...]}``."""
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError) as exc:  # ValueError: JSON and UTF-8 decode errors
        raise ValueError(f"{p}: cannot read ARKit name mapping ({exc})") from None
    if not isinstance(data, dict) or not all(isinstance(v, str | list) for v in data.values()):
        raise ValueError(f"{p}: mapping must be a JSON object of ARKit name -> rig shape name(s)")
    return data


def head_angles(quat_xyzw: np.ndarray) -> np.ndarray:
    """Head yaw, pitch, roll in radians from a head rotation (x, y, z, w).

    Axes of livecap's head frame: +y up (yaw), +x towards the subject's left (pitch), +z out of
    the face (roll); intrinsic Y-X-Z order.
    """
    return np.array(head_yaw_pitch_roll(np.asarray(quat_xyzw, dtype=float).tolist()))


def head_yaw_pitch_roll(quat_xyzw: list[float]) -> tuple[float, float, float]:
    """:func:`head_angles` of four Python floats (a per-packet path: no numpy call, docs/iphone.md); 0s for a
    zero or non-finite quaternion."""
    x, y, z, w = quat_xyzw
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n) or n < 1e-9:
        return 0.0, 0.0, 0.0
    x, y, z, w = x / n, y / n, z / n, w / n  # the matrix entries of R = Ry(yaw) Rx(pitch) Rz(roll) that give them
    return (math.atan2(2 * (x * z + w * y), 1 - 2 * (x * x + y * y)),
            math.asin(min(1.0, max(-1.0, -2 * (y * z - w * x)))),
            math.atan2(2 * (x * y + w * z), 1 - 2 * (x * x + z * z)))
