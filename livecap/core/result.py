"""What a solve produces per frame: the unit every sink publishes and the viewer draws."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BOUND_TOL = 1e-6  # a weight this close to its lower/upper limit sits at the bound


@dataclass
class SolveResult:
    frame: int
    timestamp: float  # seconds, the source frame's timestamp
    names: list[str]  # shape names (shared, not copied per frame)
    weights: np.ndarray  # m
    head_rotation: np.ndarray  # 4, quaternion (x, y, z, w); raw = R @ stabilised + t
    head_translation: np.ndarray  # 3, mm
    residual: float = 0.0  # RMS marker residual of the fit, mm
    solve_time: float = 0.0  # seconds spent in the solver for this frame
    markers: np.ndarray | None = None  # n x 3 stabilised markers (head frame, mm), for previews
    valid: np.ndarray | None = None  # n bool
    at_bound: np.ndarray | None = None  # m int8: -1 at the lower limit, +1 at the upper, 0 inside
    received: float | None = None  # wall clock (time.time()) its frame reached livecap (timecode at capture)
