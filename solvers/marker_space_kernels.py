"""Compiled (numba) element-wise parts of a block-pivoting pass of ``solvers.marker_space_qp``.

Why: at 72 x 1000 a pass's work over the 1006 weights (the right side, x and the gradient from the fitted markers,
the new partition and its count of wrong sides) took ~35 µs as a dozen whole-array numpy calls, beside ~50 µs for its
two 216 x 1006 products (docs/performance.md, "`kalman` at 72 x 1000", 2026-12-05 afternoon). One loop each here,
the same arithmetic in the same order (so the same bits). ``cache=True``: only a process's first run compiles.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def rhs(fG: np.ndarray, dinv: np.ndarray, lo: np.ndarray, hi: np.ndarray, at_lo: np.ndarray,
        at_hi: np.ndarray) -> np.ndarray:
    """-D^-1 f on the free weights, the limit on the bounded ones (J of this is the subproblem's right side)."""
    v = np.empty(fG.shape[0])
    for i in range(fG.shape[0]):
        v[i] = lo[i] if at_lo[i] else (hi[i] if at_hi[i] else -fG[i] * dinv[i])
    return v


@numba.njit(cache=True, nogil=True)
def x_and_gradient(z: np.ndarray, fG: np.ndarray, d: np.ndarray, dinv: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                   at_lo: np.ndarray, at_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x = -D^-1 (f + J'y) on the free weights, the limits elsewhere; the gradient D x + J'y + f (z = J'y)."""
    n = fG.shape[0]
    x, g = np.empty(n), np.empty(n)
    for i in range(n):
        xi = lo[i] if at_lo[i] else (hi[i] if at_hi[i] else -(fG[i] + z[i]) * dinv[i])
        x[i] = xi
        g[i] = d[i] * xi + z[i] + fG[i]
    return x, g


@numba.njit(cache=True, nogil=True)
def repartition(x: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray, at_lo: np.ndarray,
                at_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Block pivoting's next partition: a free weight outside a limit is bounded there, a bounded one whose
    multiplier has the wrong sign is freed; and how many weights changed sides."""
    n = x.shape[0]
    lo1, hi1 = np.empty(n, np.bool_), np.empty(n, np.bool_)
    wrong = 0
    for i in range(n):
        if at_lo[i] or at_hi[i]:
            a, b = at_lo[i] and g[i] >= 0, at_hi[i] and g[i] <= 0
        else:
            a, b = x[i] <= lo[i], x[i] >= hi[i]
        lo1[i], hi1[i] = a, b
        if a != at_lo[i] or b != at_hi[i]:
            wrong += 1
    return lo1, hi1, wrong
