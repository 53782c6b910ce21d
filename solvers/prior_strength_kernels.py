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
