"""Whittaker smoothing of many tracks with gaps at once (Eilers 2003, "A perfect smoother",
Anal. Chem. 75: 3631): minimise sum_t v_t |x_t - y_t|^2 + lam sum_t |x_{t+1} - 2 x_t + x_{t-1}|^2
with v_t = 1 where a sample is seen and 0 where it is missing. Where nothing is seen the minimiser
is a cubic in t (a discrete cubic smoothing spline), so gaps are bridged by cubics that continue
the smoothed track on both sides.

Each track's system is pentadiagonal, factored and solved by one LDL' sweep over time for each candidate
smoothing, O(frames) per track and candidate (compiled: solvers.whittaker_kernels).
The smoothing is chosen per track by generalised cross validation (Craven & Wahba 1979), with the
hat matrix trace from the cosine-basis eigenvalues of the second-difference penalty.
"""

from __future__ import annotations

import numpy as np

LAMBDAS = 10.0 ** np.arange(-1.0, 7.01, 1.0)  # smoothing candidates (frames^4)
_OMEGA = np.pi * (np.arange(4096) + 0.5) / 4096
_DOF_FRACTION = np.mean(1.0 / (1.0 + LAMBDAS[:, None] * (2.0 - 2.0 * np.cos(_OMEGA)) ** 2), axis=1)


def _penalty_bands(T: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Diagonal, first and second off-diagonals of D2'D2 for T frames."""
    d = np.full(T, 6.0)
    d[[0, -1]] = 1.0
    d[[1, -2]] = 5.0
    e = np.full(T - 1, -4.0)
    e[[0, -1]] = -2.0
    return d, e, np.ones(T - 2)


def smooth(y: np.ndarray, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed tracks (T, k, c) for tracks ``y`` (T, k, c) seen where ``seen`` (T, k), and the
    smoothing chosen for each track. Every track needs at least two seen samples. Tracks are
    independent; each is swept by the compiled kernel (solvers.whittaker_kernels), imported here so that
    importing this module does not import numba."""
    from solvers.whittaker_kernels import smooth_tracks

    y = np.ascontiguousarray(np.swapaxes(y, 0, 1), dtype=np.float64)  # track-major: a track's frames in one run
    seen = np.ascontiguousarray(np.asarray(seen, dtype=bool).T)
    x, best = smooth_tracks(y, seen, *_penalty_bands(y.shape[1]), LAMBDAS, _DOF_FRACTION)
    return np.swapaxes(x, 0, 1), LAMBDAS[best]
