"""Compiled (numba) scoring of a held-out strength trial (``solvers.prior_strength``).

Why compiled: the score is a dozen rows of the basis times the trial's weights against the held-out markers;
as numpy calls (a fancy index of the rows, a product, a difference, a dot) it cost a streamed trial ~4 calls
of overhead on ~20 numbers (issue 39, docs/performance.md "`kalman` against `robust`").
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def held_out_error(basis: np.ndarray, markers: np.ndarray, seen: np.ndarray, w: np.ndarray,
                   target: np.ndarray) -> float:
    """Sum of squared errors of B w against ``target`` over the rows of ``markers`` whose ``seen`` is set."""
    acc = 0.0
    for q in range(markers.shape[0]):
        if not seen[q]:
            continue
        for r in range(3 * markers[q], 3 * markers[q] + 3):
            b = basis[r]
            p = 0.0
            for j in range(w.shape[0]):
                p += b[j] * w[j]
            d = p - target[r]
            acc += d * d
    return acc


@numba.njit(cache=True, nogil=True)
def unbounded_trial(target: np.ndarray, valid: np.ndarray, basis: np.ndarray, fill: np.ndarray, rows: np.ndarray,
                    GT: np.ndarray, h: np.ndarray, lower: np.ndarray, upper: np.ndarray, markers: np.ndarray,
                    g: int, d: float, err: np.ndarray, count: np.ndarray, counted: bool) -> int:
    """A streamed held-out trial (``HeldOutStrength.observe_unbounded``) and its score: the training ``rows``'
    targets, those of markers not ``valid`` predicted by ``fill`` (B fill), through the fit without bounds
    w = G x + h (``GT`` = G', rows x m: each weight's sum in the same order, the rows' loop vectorised), clipped to
    [lower, upper]; :func:`held_out_error` of w on the held-out ``markers`` that are valid added to ``err[g]`` and
    their number to ``count[g]``, both decayed by ``d`` first (``HeldOutStrength._score``). Returns the strength
    with the least mean error where every count is > 0 (or ``counted``) (:func:`score`), else -1 (also when nothing
    is scored and nothing decayed: no held-out marker valid, or fewer than 3 training markers). Why one call: the
    score's six numpy calls on nine numbers cost ~3 µs of a ~11 µs trial (issue 39)."""
    seen = np.empty(markers.shape[0], np.bool_)
    held = 0
    for q in range(markers.shape[0]):
        seen[q] = valid[markers[q]]
        held += seen[q]
    train = 0
    for i in range(0, rows.shape[0], 3):
        train += valid[rows[i] // 3]
    if held == 0 or train < 3:
        return -1
    m = GT.shape[1]
    w = h.copy()
    for i in range(rows.shape[0]):
        r = rows[i]
        if valid[r // 3]:
            xi = target[r]
        else:
            b = basis[r]
            xi = 0.0
            for j in range(fill.shape[0]):
                xi += b[j] * fill[j]
        gi = GT[i]
        for j in range(m):
            w[j] += gi[j] * xi
    for j in range(m):
        w[j] = min(max(w[j], lower[j]), upper[j])
    return score(err, count, g, held_out_error(basis, markers, seen, w, target), held, d, counted)


@numba.njit(cache=True, nogil=True)
def score(err: np.ndarray, count: np.ndarray, g: int, e: float, held: float, d: float, counted: bool) -> int:
    """A trial's score (every trial's, ``HeldOutStrength._score``): ``err`` and ``count`` decayed by ``d``, the
    trial's error ``e`` and its ``held`` markers added to strength ``g``'s. Returns the strength with the least mean
    error where every count is > 0 (or ``counted``), else -1."""
    K = err.shape[0]
    for k in range(K):
        err[k] *= d
        count[k] *= d
    err[g] += e
    count[g] += held
    if not counted:
        for k in range(K):
            if not count[k] > 0:
                return -1
    best, arg = np.inf, 0
    for k in range(K):
        v = err[k] / count[k]
        if v != v:  # as np.argmin: the first NaN
            return k
        if v < best:
            best, arg = v, k
    return arg
