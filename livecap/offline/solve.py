"""Offline solve of a recorded take: stabilise every frame, then run a solver over the take."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from livecap.calibration.gaps import fill_gaps
from livecap.calibration.profile import Profile
from livecap.calibration.stabilise import smooth_pose, to_quaternion
from livecap.core.take import Take
from livecap.modes.robust_take import whole_take

DEFAULT_MAX_GAP_SECONDS = 0.25  # Curio §2.1 fills gaps by spline; longer gaps stay missing
DEFAULT_POSE_SMOOTHING_SECONDS = 0.2  # offline head-pose smoothing window (see stabilise.smooth_pose)


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


def max_gap_frames(profile: Profile, rate: float, max_gap_seconds: float | None = None) -> int:
    """Longest gap (frames) the offline path fills: the argument, else the profile's
    ``max_gap_seconds`` setting, else DEFAULT_MAX_GAP_SECONDS; 0 disables filling."""
    sec = max_gap_seconds if max_gap_seconds is not None else profile.settings.get("max_gap_seconds",
                                                                                   DEFAULT_MAX_GAP_SECONDS)
    return max(0, int(round(float(sec) * rate)))


def prepare_targets(take: Take, profile: Profile, max_gap_seconds: float | None = None,
                    stabiliser=None, pose_smoothing_seconds: float | None = None):
    """Stabilised marker displacements from the actor's neutral, plus the head pose.

    Head motion is removed by the profile's (robust) stabiliser (Seol §3.1), the pose smoothed
    over ``pose_smoothing_seconds`` (default: the profile's setting, else 0.2 s; 0 = raw), then
    interior gaps up to ``max_gap_seconds`` are filled from each marker's smoothed track in the head frame (Curio
    §2.1). Returns
    the take (labels in profile order, valid mask including filled samples, filled positions put
    back in capture space), targets (T, n, 3; 0 where still missing, never NaN), R and t.
    """
    take = take.select(profile.labels)
    stab = stabiliser if stabiliser is not None else profile.stabiliser()
    local, R, t = stab.stabilise(take.positions, take.valid)
    sec = pose_smoothing_seconds if pose_smoothing_seconds is not None else profile.settings.get(
        "pose_smoothing_seconds", DEFAULT_POSE_SMOOTHING_SECONDS)
    window = int(round(float(sec) * take.rate)) | 1
    if window > 3:
        R, t = smooth_pose(R, t, window)
        local = (take.positions - t[:, None, :]) @ R  # R^T per frame, as a batched matmul
        local = np.where(take.valid[..., None], local, 0.0)
    gap = max_gap_frames(profile, take.rate, max_gap_seconds)
    if gap > 0:
        local, valid = fill_gaps(local, take.valid, gap)
        raw = local @ np.swapaxes(R, 1, 2) + t[:, None, :]
        take = Take(take.labels, raw, valid, take.rate, take.first_frame)
    targets = np.where(take.valid[..., None], local - profile.source_neutral, 0.0)
    return take, targets, R, t


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
