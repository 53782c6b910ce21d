"""Offline solve of a recorded take: stabilise every frame, then run a solver over the take."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from livecap.calibration.profile import Profile
from livecap.calibration.stabilise import to_quaternion
from livecap.calibration.targets import (  # noqa: F401 - the names offline callers import from here
    DEFAULT_MAX_GAP_SECONDS,
    DEFAULT_POSE_SMOOTHING_SECONDS,
    max_gap_frames,
    prepare_targets,
)
from livecap.core.take import Take
from livecap.modes.robust_take import whole_take


@dataclass
class SolvedTake:
    names: list[str]
    weights: np.ndarray  # T x m
    head_rotation: np.ndarray  # T x 4 (x, y, z, w)
    head_translation: np.ndarray  # T x 3 mm
    targets: np.ndarray  # T x n x 3 stabilised displacements from the neutral
    valid: np.ndarray  # T x n
    rate: float
    first_frame: int
    solve_seconds: float


def solve_take(take: Take, profile: Profile, solver, progress=None,
               max_gap_seconds: float | None = None, stabiliser=None,
               pose_smoothing_seconds: float | None = None) -> SolvedTake:
    """Run ``solver`` over every frame; solvers with ``solve(targets, valid)`` do it in one go, and the
    robust mode's stages run over the whole take (:func:`livecap.modes.robust_take.whole_take`).

    ``max_gap_seconds``: gaps filled before solving (see :func:`prepare_targets`; 0 = none);
    ``stabiliser``: anything with ``stabilise(positions, valid)`` in place of the profile's;
    ``pose_smoothing_seconds``: offline head-pose smoothing (0 = none).
    """
    take, targets, R, t = prepare_targets(take, profile, max_gap_seconds, stabiliser, pose_smoothing_seconds)
    start = time.perf_counter()
    if hasattr(solver, "solve"):
        W = solver.solve(targets, take.valid)
    elif (W := whole_take(solver, targets, take.valid)) is not None:
        if progress is not None:
            progress(take.n_frames, take.n_frames)
    else:
        W = np.zeros((take.n_frames, len(profile.names)))
        for i in range(take.n_frames):
            W[i] = solver.step(targets[i], take.valid[i])
            if progress is not None:
                progress(i + 1, take.n_frames)
    elapsed = time.perf_counter() - start
    return SolvedTake(list(profile.names), W, to_quaternion(R), t, targets, take.valid, take.rate,
                      take.first_frame, elapsed)
