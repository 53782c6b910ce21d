"""A take's markers as a solve's targets: head motion removed, gaps filled, displacements from the actor's
neutral. Calibration's last step and every offline solve's first (livecap.offline.solve), so it sits here."""

from __future__ import annotations

import numpy as np

from livecap.calibration.gaps import fill_gaps
from livecap.calibration.profile import Profile
from livecap.calibration.stabilise import smooth_pose
from livecap.core.take import Take

DEFAULT_MAX_GAP_SECONDS = 0.25  # Curio §2.1 fills gaps by spline; longer gaps stay missing
DEFAULT_POSE_SMOOTHING_SECONDS = 0.2  # offline head-pose smoothing window (see stabilise.smooth_pose)


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
