"""Compiled (numba) rank-1 up- and downdates of a lower Cholesky factor (``solvers.marker_space_qp``).

Why: a weight entering (leaving) the free set changes S = I + J_F D_F^-1 J_F' by +w w' (-w w'); k such changes cost
~2 k r^2 multiply-adds through the factor against r^3 / 3 for a refactor (Golub & Van Loan 2013 §6.5.4; the
downdate by hyperbolic rotations, Stewart 1979). scipy has no cholupdate. The factor is Fortran-ordered so each
column's loop runs over contiguous memory; only the lower triangle is read or written.
``cache=True`` keeps the machine code in ``__pycache__`` so only a process's first run compiles.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def lowrank_update(L: np.ndarray, X: np.ndarray, sign: np.ndarray) -> bool:
    """L L' + sum_j sign[j] X[:, j] X[:, j]' into ``L`` in place (lower triangle), the columns in order; ``X`` is
    overwritten. False where a downdate would leave the matrix not positive definite (``L`` then partly changed)."""
    n = L.shape[0]
    x = np.empty(n)
    for j in range(X.shape[1]):
        for i in range(n):
            x[i] = X[i, j]
        s_j = sign[j]
        for k in range(n):
            lkk = L[k, k]
            xk = x[k]
            r2 = lkk * lkk + s_j * xk * xk
            if not r2 > 0.0:
                return False
            r = math.sqrt(r2)
            c = r / lkk
            s = xk / lkk
            L[k, k] = r
            ci = 1.0 / c
            for i in range(k + 1, n):
                lik = (L[i, k] + s_j * s * x[i]) * ci
                L[i, k] = lik
                x[i] = c * x[i] - s * lik
    return True
