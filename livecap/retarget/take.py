"""A Live Link Face CSV as a solved take of any rig: the curves on the timecode's 60 fps grid, retargeted."""

from __future__ import annotations

import time

import numpy as np

from livecap.offline.solve import SolvedTake
from transport.livelink_source import head_quaternion
from transport.llf_csv import TIMECODE_RATE, ArkitCurves


def head_quaternions(yaw_pitch_roll: np.ndarray) -> np.ndarray:
    """T x 4 (x, y, z, w) rotations Ry(yaw) Rx(pitch) Rz(roll): the app's angles, as the live source reads them."""
    return np.array([head_quaternion(r) for r in np.asarray(yaw_pitch_roll, dtype=float)]).reshape(-1, 4)


def retarget_curves(curves: ArkitCurves, retarget) -> SolvedTake:
    """Every timecode frame from the first row to the last (linear between rows, the app writes about
    every second one), its weights from ``retarget.apply`` and the head rotation of the row's angles;
    ``first_frame`` is the first row's timecode frame, so the take keeps the app's timecode."""
    arkit, head, _ = curves.resample_all(TIMECODE_RATE)
    T = len(arkit)
    t0 = time.perf_counter()
    W = retarget.apply(arkit)
    seconds = time.perf_counter() - t0
    quats = head_quaternions(head) if head is not None else np.tile([0.0, 0.0, 0.0, 1.0], (T, 1))
    return SolvedTake(list(retarget.names), W, quats, np.zeros((T, 3)), np.zeros((T, 0, 3)), np.zeros((T, 0), bool),
                      TIMECODE_RATE, curves.first_frame, seconds)
