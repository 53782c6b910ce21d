"""Gaps in marker trajectories (Curio et al. 2006 §2.1: "gaps in any marker trajectory filled by
cubic spline interpolation").

Offline, interior gaps up to ``max_gap`` frames are filled; longer gaps, and gaps at the start or
end of the take (nothing to interpolate towards), stay missing with ``valid`` False. Online nothing
is filled: the solver gets the valid mask and drops or imputes the rows, and no NaN is ever passed on.

Each gap is bridged by a discrete cubic smoothing spline (Whittaker smoother,
:mod:`solvers.whittaker`) fitted to the marker's track within ``CONTEXT`` frames on either side,
its smoothing chosen by generalised cross validation as the per-gap spline it replaced did
(:mod:`livecap.calibration.gaps_spline`): a curve through every noisy sample would turn 0.5 mm of
noise into centimetres of overshoot in a long gap. All gaps of all markers, all axes and all
candidate smoothings are solved in one vectorised banded sweep over the window: O(frames) per
marker, no Python loop over gaps.

Fill in the stabilised (head) frame, where a trajectory is the expression alone: head rotation
is not a cubic in time, the expression is smoother.
"""

from __future__ import annotations

import numpy as np

from solvers.whittaker import smooth

CONTEXT = 64  # frames of the track on either side of a gap that its smoothed bridge is fitted to


def gap_runs(valid: np.ndarray) -> list[tuple[int, int]]:
    """Runs [start, stop) of False in a 1-D mask."""
    v = np.concatenate([[True], np.asarray(valid, bool), [True]])
    edges = np.flatnonzero(np.diff(v.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[0::2], edges[1::2], strict=True)]


def gap_table(valid: np.ndarray, max_gap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marker, start and stop of every interior gap of at most ``max_gap`` frames."""
    valid = np.asarray(valid, bool)
    T, n = valid.shape
    pad = np.ones((T + 2, n), bool)
    pad[1:-1] = valid
    step = np.diff(pad.astype(np.int8), axis=0).T  # (n, T + 1): -1 where a gap starts, +1 after it ends
    marker, start = np.nonzero(step == -1)
    _, stop = np.nonzero(step == 1)
    keep = (start > 0) & (stop < T) & (stop - start <= max_gap)
    return marker[keep], start[keep], stop[keep]


def fill_gaps(positions: np.ndarray, valid: np.ndarray, max_gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Copies of ``positions`` (T, n, 3) and ``valid`` (T, n) with short interior gaps filled.

    A gap is filled only when it has at most ``max_gap`` frames and visible samples on both sides,
    from the marker's smoothed track (module docstring); seen samples are untouched, positions that
    stay missing are 0.
    """
    positions = np.array(positions, dtype=np.float64)
    valid = np.array(valid, dtype=bool)
    T = len(valid)
    if max_gap <= 0 or T < 3:
        positions[~valid] = 0.0
        return positions, valid
    marker, start, stop = gap_table(valid, max_gap)
    if len(marker):
        span = 2 * CONTEXT + int((stop - start).max())
        rows = start[None, :] - CONTEXT + np.arange(span)[:, None]  # (span, gaps) frames of each window
        inside = (rows >= 0) & (rows < T)
        at = np.clip(rows, 0, T - 1)
        curve, _ = smooth(positions[at, marker[None, :]], valid[at, marker[None, :]] & inside)
        own = (rows >= start) & (rows < stop)
        positions[rows[own], np.broadcast_to(marker, rows.shape)[own]] = curve[own]
        valid[rows[own], np.broadcast_to(marker, rows.shape)[own]] = True
    filled = valid
    positions[~filled] = 0.0
    return positions, filled
