"""Eye angles from the eye-look shapes: the one derivation every sink uses (VMC eye bones, Live Link
Face packets and CSV rows), so a rig with eyeLook shapes turns a receiver's eyes the same way.

A full look shape turns the eye ``EYE_YAW`` sideways or ``EYE_PITCH`` up/down. Signs are the Live
Link Face app's: +yaw turns the eye towards the subject's right, +pitch turns it down. Measured on
the six real app CSVs in ../shared/realdata/performance (least squares of the app's eye angles on
the look shapes, 2026-12-04): yaw 0.49-0.61 rad and pitch 0.44-0.61 rad per unit look, r >= 0.94
on the five longer takes; 30 and 25 degrees (0.52, 0.44 rad) sit inside both ranges.
"""

from __future__ import annotations

import numpy as np

EYE_YAW = np.radians(30.0)
EYE_PITCH = np.radians(25.0)
LOOKS = ("Out", "In", "Down", "Up")  # column order of :func:`eye_angles`' input
_OUTWARD = (-1.0, 1.0)  # the left eye looks out towards the subject's left


def eye_angles(looks: np.ndarray, yaw: float = EYE_YAW, pitch: float = EYE_PITCH) -> np.ndarray:
    """2 x 2 (left, right) x (yaw, pitch) radians from ``looks``, 2 x 4 weights of eyeLook
    Out, In, Down, Up for the left and the right eye."""
    # Python floats: it runs per packet, where each small numpy operation costs more (docs/iphone.md, Latency)
    (o0, i0, d0, u0), (o1, i1, d1, u1) = np.asarray(looks, dtype=float).reshape(2, 4).tolist()
    s0, s1 = _OUTWARD
    return np.array([[yaw * s0 * (o0 - i0), pitch * (d0 - u0)], [yaw * s1 * (o1 - i1), pitch * (d1 - u1)]])
