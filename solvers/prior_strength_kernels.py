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
                    G: np.ndarray, h: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                    markers: np.ndarray) -> tuple[float, int]:
    """A streamed held-out trial (``HeldOutStrength.observe_unbounded``): the training ``rows``' targets, those of
    markers not ``valid`` predicted by ``fill`` (B fill), through the fit without bounds w = G x + h, clipped to
    [lower, upper]; returns :func:`held_out_error` of w on the held-out ``markers`` that are valid, and their
    number (0, and no fit, when none is valid or fewer than 3 training markers are)."""
    seen = np.empty(markers.shape[0], np.bool_)
    held = 0
    for q in range(markers.shape[0]):
        seen[q] = valid[markers[q]]
        held += seen[q]
    train = 0
    for i in range(0, rows.shape[0], 3):
        train += valid[rows[i] // 3]
    if held == 0 or train < 3:
        return 0.0, 0
    x = np.empty(rows.shape[0])
    for i in range(rows.shape[0]):
        r = rows[i]
        if valid[r // 3]:
            x[i] = target[r]
        else:
            b = basis[r]
            acc = 0.0
            for j in range(fill.shape[0]):
                acc += b[j] * fill[j]
            x[i] = acc
    m = G.shape[0]
    w = np.empty(m)
    for j in range(m):
        g = G[j]
        acc = h[j]
        for i in range(x.shape[0]):
            acc += g[i] * x[i]
        w[j] = min(max(acc, lower[j]), upper[j])
    return held_out_error(basis, markers, seen, w, target), held
