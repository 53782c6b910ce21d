"""Eye angles from the eye-look shapes: the one derivation every sink uses (VMC eye bones, Live Link
Face packets and CSV rows), so a rig with eyeLook shapes turns a receiver's eyes the same way.

A full look shape turns the eye ``EYE_YAW`` sideways or ``EYE_PITCH`` up/down. Signs are the Live
Link Face app's: +yaw turns the eye towards the subject's right, +pitch turns it down. Measured on
the six real app CSVs in ../shared/realdata/performance (least squares of the app's eye angles on
the look shapes, 2026-12-04): yaw 0.49-0.61 rad and pitch 0.44-0.61 rad per unit look, r >= 0.94
on the five longer takes; 30 and 25 degrees (0.52, 0.44 rad) sit inside both ranges.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

EYE_YAW = math.radians(30.0)
EYE_PITCH = math.radians(25.0)
LOOKS = ("Out", "In", "Down", "Up")  # column order of :func:`eye_angles`' input


def eye_angles(looks: np.ndarray, yaw: float = EYE_YAW, pitch: float = EYE_PITCH) -> np.ndarray:
    """2 x 2 (left, right) x (yaw, pitch) radians from ``looks``, 2 x 4 weights of eyeLook
    Out, In, Down, Up for the left and the right eye."""
    return np.array(eye_yaw_pitch(np.asarray(looks, dtype=float).ravel().tolist(), yaw, pitch)).reshape(2, 2)


def eye_yaw_pitch(looks: Sequence[float], yaw: float = EYE_YAW, pitch: float = EYE_PITCH) -> tuple[float, ...]:
    """:func:`eye_angles` in Python floats, flat: left yaw, left pitch, right yaw, right pitch from the 8 looks
    (left Out, In, Down, Up, then the right's). Per packet numpy's per-call cost dominates (docs/iphone.md, Latency)."""
    o0, i0, d0, u0, o1, i1, d1, u1 = looks
    return -yaw * (o0 - i0), pitch * (d0 - u0), yaw * (o1 - i1), pitch * (d1 - u1)  # the left eye's out is -yaw
