"""Per-take quality figures a supervisor scans to find bad takes."""

from __future__ import annotations

import numpy as np

from livecap.calibration.profile import Profile
from livecap.core.take import Take
from livecap.offline.solve import SolvedTake

BOUND_TOL = 1e-6
MISSING_FLAG = 0.10  # a take missing more than this share of marker-frames gets a warning
UPPER_FLAG = 0.05  # ... or with more than this share of weight samples pinned at their upper limit


def frame_residual(solved: SolvedTake, profile: Profile) -> np.ndarray:
    """RMS marker residual per frame (mm) of the linear marker model at the solved weights, over the
    markers seen in that frame (NaN when none); the same fit error ``livecap calibration-report`` prints."""
    T, n, _ = solved.targets.shape
    err = solved.targets.reshape(T, 3 * n) - solved.weights @ profile.basis.T
    err *= err  # in place: a take's T x 3n temporaries are most of this function's cost
    sq = err.reshape(solved.targets.shape).sum(axis=2)
    count = solved.valid.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.where(solved.valid, sq, 0.0).sum(axis=1) / count)


def missing_share(take: Take, labels: list[str]) -> float:
    """Share of the marker-frames of ``labels`` the take lacks (a label it does not have: every frame), what
    ``1 - take.select(labels).valid.mean()`` is, without copying the take's positions."""
    if not take.n_frames or not labels:
        return 1.0
    where = {lab: i for i, lab in enumerate(take.labels)}
    seen = take.valid[:, [where[lab] for lab in labels if lab in where]].sum()
    return float(1.0 - seen / (take.n_frames * len(labels)))


def take_stats(take: Take, solved: SolvedTake, profile: Profile) -> dict:
    res = frame_residual(solved, profile)
    seen = res[np.isfinite(res)]
    W = solved.weights
    lower, upper = np.broadcast_to(profile.lower, W.shape), np.broadcast_to(profile.upper, W.shape)
    at_lower = float(np.mean(W <= lower + BOUND_TOL)) if W.size else 0.0
    at_upper = float(np.mean(W >= upper - BOUND_TOL)) if W.size else 0.0
    missing = missing_share(take, profile.labels)
    flags = []
    if missing > MISSING_FLAG:
        flags.append(f"{missing:.0%} of marker-frames missing")
    if at_upper > UPPER_FLAG:
        flags.append(f"{at_upper:.1%} of weight samples at their upper limit")
    return {
        "frames": int(take.n_frames), "rate": float(take.rate), "duration_s": take.n_frames / take.rate,
        "solve_seconds": float(solved.solve_seconds),
        "residual_p50_mm": float(np.percentile(seen, 50)) if seen.size else float("nan"),
        "residual_p95_mm": float(np.percentile(seen, 95)) if seen.size else float("nan"),
        "missing_share": missing, "at_lower_share": at_lower, "at_upper_share": at_upper,
        "names": list(solved.names),
        "weight_min": W.min(axis=0).tolist() if len(W) else [], "weight_max": W.max(axis=0).tolist() if len(W) else [],
        "flags": flags, "frame_residual_mm": res,
    }
