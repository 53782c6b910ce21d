"""Compiled (numba) per-frame quality figures of a blendshape fit, for the live pipeline's ``SolveResult``.

Why compiled: the RMS marker residual (fitted minus observed over the markers seen) and the at-bound flags
were eight array calls a frame around a 180 x 43 product, each costing several times its tight-loop figure
when the driver is paced at 120 Hz (docs/performance.md, "The live driver's own cost"). Equal to the numpy
expressions to rounding (tests/test_pipeline.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def fit_quality(basis, w, target, valid, lower, upper):
    """RMS over the ``valid`` markers of ``basis @ w - target`` per coordinate (0 when none is valid), and per
    weight +1 at or above ``upper``, -1 at or below ``lower``, else 0 (int8)."""
    n = target.shape[0]
    m = w.shape[0]
    total = 0.0
    seen = 0
    for i in range(n):
        if not valid[i]:
            continue
        seen += 1
        for c in range(3):
            row = 3 * i + c
            s = 0.0
            for k in range(m):
                s += basis[row, k] * w[k]
            d = s - target[i, c]
            total += d * d
    at_bound = np.zeros(m, np.int8)
    for k in range(m):
        at_bound[k] = (w[k] >= upper[k]) - (w[k] <= lower[k])
    return (math.sqrt(total / seen / 3.0) if seen else 0.0), at_bound
