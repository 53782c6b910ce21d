"""The per-gap smoothing-spline fill that livecap.calibration.gaps replaced, kept as the reference
its accuracy is tested and benchmarked against (one spline fit per gap per axis: slow on long,
heavily occluded takes). Curio et al. 2006 §2.1: "gaps in any marker trajectory filled by cubic
spline interpolation".

Offline, interior gaps up to ``max_gap`` frames are filled by a cubic smoothing spline through the
marker's visible samples around the gap; longer gaps, and gaps at the start or end of the take (nothing to interpolate
towards), stay missing with ``valid`` False. Online nothing is filled: the solver gets the valid
mask and drops or imputes the rows, and no NaN is ever passed on.

Fill in the stabilised (head) frame, where a trajectory is the expression alone: head rotation
is not a cubic in time, the expression is smoother.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import make_smoothing_spline

from livecap.calibration.gaps import gap_runs


def _end(frames: np.ndarray, values: np.ndarray, at: int) -> tuple[np.ndarray, np.ndarray]:
    """Position and velocity (per frame) at frame ``at`` from a least-squares line through samples."""
    if len(frames) < 2:
        return values[0], np.zeros(values.shape[1])
    dt = (frames - at).astype(np.float64)
    A = np.stack([np.ones_like(dt), dt], 1)
    coef, *_ = np.linalg.lstsq(A, values, rcond=None)
    return coef[0], coef[1]


def _hermite(positions: np.ndarray, col: np.ndarray, j: int, a: int, b: int, k: int) -> np.ndarray:
    """Cubic Hermite segment over [a, b) with end conditions from lines through nearby samples."""
    left = np.flatnonzero(col[max(0, a - k):a]) + max(0, a - k)
    right = np.flatnonzero(col[b:b + k]) + b
    p0, v0 = _end(left[-k:], positions[left[-k:], j], a - 1)
    p1, v1 = _end(right[:k], positions[right[:k], j], b)
    h = b - (a - 1)
    s = (np.arange(a, b) - (a - 1))[:, None] / h
    s2, s3 = s * s, s * s * s
    return ((2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * h * v0
            + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * h * v1)


def fill_gaps_per_gap(positions: np.ndarray, valid: np.ndarray, max_gap: int,
              window: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Copies of ``positions`` (T, n, 3) and ``valid`` (T, n) with short interior gaps filled.

    A gap is filled only when it has at most ``max_gap`` frames and visible samples on both sides.
    Each gap is bridged by a cubic smoothing spline (smoothing chosen by generalised cross
    validation) through the visible samples within max(8, gap length) frames, at most ``window``,
    on either side: an interpolating spline through every noisy sample would turn 0.5 mm of
    noise into centimetres of overshoot in a long gap. With fewer than 5 samples around, a cubic
    Hermite segment with end velocities from nearby samples. Positions that stay missing are 0.
    """
    positions = np.array(positions, dtype=np.float64)
    valid = np.array(valid, dtype=bool)
    T = len(valid)
    if max_gap <= 0 or T < 3:
        positions[~valid] = 0.0
        return positions, valid
    filled = valid.copy()
    for j in range(valid.shape[1]):
        col = valid[:, j]
        if col.all() or col.sum() < 2:
            continue
        for a, b in gap_runs(col):
            if a == 0 or b == T or b - a > max_gap:
                continue
            k = int(np.clip(b - a, 8, window))
            lo, hi = max(0, a - k), min(T, b + k)
            frames = np.flatnonzero(col[lo:hi]) + lo
            if len(frames) >= 5:
                x = frames.astype(np.float64)
                for c in range(3):
                    spline = make_smoothing_spline(x, positions[frames, j, c])
                    positions[a:b, j, c] = spline(np.arange(a, b, dtype=np.float64))
            else:
                positions[a:b, j] = _hermite(positions, col, j, a, b, 4)
            filled[a:b, j] = True
    positions[~filled] = 0.0
    return positions, filled
