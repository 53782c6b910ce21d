"""Compiled (numba) helpers of ``solvers.qp``'s workspace building: the smallest eigenvalue of a small symmetric
block (the unpenalised pose columns' 6 x 6), once per new visibility pattern; a pattern's H by a downdate; its whole
workspace (H, the check's numbers and the box QP's state) in one call.

Why compiled: numpy's ``eigvalsh`` costs 10-50 µs of call overhead on a 6 x 6 (docs/performance.md,
"kalman's streamed step"); cyclic Jacobi rotations (Golub & Van Loan 2013 §8.5.2) in a loop take a few.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from solvers.box_qp_kernels import state as box_state


@numba.njit(cache=True, nogil=True)
def smallest_eigenvalue(A_in: np.ndarray) -> float:
    """The smallest eigenvalue of the symmetric ``A_in`` (cyclic Jacobi, to rounding), less a margin of
    1e-12 of its trace so that it never exceeds the true one."""
    A = A_in.copy()
    n = A.shape[0]
    scale = 0.0
    for i in range(n):
        scale += abs(A[i, i])
    for _ in range(60):
        off = 0.0
        for p in range(n):
            for q in range(p + 1, n):
                off += A[p, q] * A[p, q]
        if off <= 1e-36 * scale * scale:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                if abs(theta) > 1e150:
                    t = 0.5 / theta
                else:
                    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):
                    akp, akq = A[k, p], A[k, q]
                    A[k, p], A[k, q] = c * akp - s * akq, s * akp + c * akq
                for k in range(n):
                    apk, aqk = A[p, k], A[q, k]
                    A[p, k], A[q, k] = c * apk - s * aqk, s * apk + c * aqk
    low = np.inf
    for i in range(n):
        low = min(low, A[i, i])
    return low - 1e-12 * scale


@numba.njit(cache=True, nogil=True)
def pattern_hessian(H_all: np.ndarray, basis: np.ndarray, row_w: np.ndarray, seen: np.ndarray, u0: int, u1: int,
                    H: np.ndarray) -> tuple[float, float]:
    """H = H_all less the rows of the markers not ``seen`` (B_r' w_r B_r each, summed before the subtraction as
    numpy's product is) into ``H``; returns trace(H) and :func:`smallest_eigenvalue` of H[u0:u1, u0:u1] (inf
    when empty). One call where a new visibility pattern took ~12 numpy calls (issue 39: the streamed step's
    new patterns were as dear as its solve, and nearly all of it call overhead)."""
    m = H_all.shape[0]
    for i in range(m):
        Hi = H[i]
        for j in range(i + 1):
            Hi[j] = 0.0
    for mk in range(seen.shape[0]):
        if seen[mk]:
            continue
        for r in range(3 * mk, 3 * mk + 3):
            b, w = basis[r], row_w[r]
            for i in range(m):
                bi = b[i]
                if bi == 0.0:
                    continue
                Hi = H[i]
                for j in range(i + 1):
                    Hi[j] += bi * (b[j] * w)
    trace = 0.0
    for i in range(m):
        Ai, Hi = H_all[i], H[i]
        for j in range(i):
            v = Ai[j] - Hi[j]
            Hi[j] = v
            H[j, i] = v
        Hi[i] = Ai[i] - Hi[i]
        trace += Hi[i]
    s2 = np.inf
    if u1 > u0:
        s2 = smallest_eigenvalue(H[u0:u1, u0:u1].copy())
    return trace, s2


@numba.njit(cache=True, nogil=True)
def pattern_workspace(H_all: np.ndarray, basis: np.ndarray, row_w: np.ndarray, seen: np.ndarray, u0: int, u1: int,
                      limit_rows: np.ndarray) -> tuple:
    """A new visibility pattern's whole workspace in one call: its rows (``seen`` per coordinate), H and what
    :func:`pattern_hessian` returns of it, and the box QP's state for H (``solvers.box_qp_kernels.state``). Why:
    as separate calls a new pattern cost ~17 µs, ~6 of them Python between the compiled parts, on the 16-18 % of
    kalman's streamed frames whose next pattern is new (issue 39)."""
    n = seen.shape[0]
    rows = np.empty(3 * n, np.bool_)
    for i in range(n):
        rows[3 * i] = rows[3 * i + 1] = rows[3 * i + 2] = seen[i]
    m = H_all.shape[0]
    H = np.empty((m, m))
    trace, s2 = pattern_hessian(H_all, basis, row_w, seen, u0, u1, H)
    V, I, meta, L, tol = box_state(H, limit_rows)
    return rows, H, trace, s2, V, I, meta, L, tol
