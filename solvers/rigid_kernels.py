"""Compiled (numba) kernel of the streamed head fit's check (``livecap.calibration.stabilise.FrameFit``).

Why compiled: a live frame's check is the plain rigid fit and its leave-one-out fits of the stable markers
(Horn 1987 §4: each rotation the top eigenvector of a symmetric 4 x 4 matrix N_j, linear in the centred points),
then every marker's residual and deleted residual. As numpy it is ~25 array calls on arrays of 6-12 markers,
whose per-call cost, several times its tight-loop figure when the driver is paced at 120 Hz, was the head fit's
cost (docs/performance.md, "The live driver's own cost"). Here it is one call: the same prepared maps, the
N_j's eigenvectors by cyclic Jacobi rotations (Golub & Van Loan 2013 §8.5) instead of LAPACK's ``dsyevd``.
Results equal the numpy version to rounding (tests/test_stabilise.py compares them with the numpy reference
in tests/head_fit_reference.py). ``cache=True`` keeps the machine code in ``__pycache__``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

PASSED, FAILED, DEGENERATE_TOP = 0, 1, 2  # the check's outcomes
_SWEEPS = 30  # a 4 x 4 converges in 4-6 sweeps; NaN input stops here and reads as degenerate


@numba.njit(cache=True, nogil=True, inline="always")
def _top_two(A, q):
    """Jacobi on the symmetric 4 x 4 ``A`` (overwritten): the largest two eigenvalues, ``q`` = the top one's
    unit eigenvector."""
    V = np.eye(4)
    for _ in range(_SWEEPS):
        off = 0.0
        diag = 0.0
        for i in range(4):
            diag += A[i, i] * A[i, i]
            for j in range(i + 1, 4):
                off += A[i, j] * A[i, j]
        if not off > 1e-36 * diag:  # also ends on NaN
            break
        for p in range(3):
            for r in range(p + 1, 4):
                apr = A[p, r]
                if apr == 0.0:
                    continue
                theta = (A[r, r] - A[p, p]) / (2.0 * apr)
                tn = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    tn = -tn
                c = 1.0 / math.sqrt(tn * tn + 1.0)
                s = tn * c
                for k in range(4):
                    akp, akr = A[k, p], A[k, r]
                    A[k, p] = c * akp - s * akr
                    A[k, r] = s * akp + c * akr
                for k in range(4):
                    apk, ark = A[p, k], A[r, k]
                    A[p, k] = c * apk - s * ark
                    A[r, k] = s * apk + c * ark
                for k in range(4):
                    vkp, vkr = V[k, p], V[k, r]
                    V[k, p] = c * vkp - s * vkr
                    V[k, r] = s * vkp + c * vkr
    top = 0
    for i in range(1, 4):
        if A[i, i] > A[top, top]:
            top = i
    second = -np.inf
    for i in range(4):
        if i != top and A[i, i] > second:
            second = A[i, i]
    norm = 0.0
    for k in range(4):
        norm += V[k, top] * V[k, top]
    norm = math.sqrt(norm)
    for k in range(4):
        q[k] = V[k, top] / norm
    return A[top, top], second


@numba.njit(cache=True, nogil=True)
def check_fit(P, Wn, Q, Zc, Lc, cs, rotation_map, limit, degenerate):
    """One frame's check against a use mask's prepared maps (``FrameFit._prepare``): ``P`` (m, 3) the points in
    use. Returns (outcome, R, t, o, p, cb): ``o`` (J, 16) each fit's q q^T, ``p`` the points centred on ``cb``
    (the plain fit's centroid); R, t the plain fit's when every residual and deleted residual is within ``limit``
    (``PASSED``), else ``FAILED`` (IRLS starts from ``o``) or ``DEGENERATE_TOP`` (a top eigenvalue near double)."""
    m = P.shape[0]
    J = Wn.shape[0]
    cb = np.zeros(3)
    for i in range(m):
        for c in range(3):
            cb[c] += Wn[0, i] * P[i, c]
    p = np.empty(3 * m)
    for i in range(m):
        for c in range(3):
            p[3 * i + c] = P[i, c] - cb[c]
    o = np.empty((J, 16))
    R = np.zeros((3, 3))
    t = np.zeros(3)
    A = np.empty((4, 4))
    q = np.empty(4)
    gap = np.inf
    biggest = -np.inf
    for j in range(J):
        for e in range(16):
            s = 0.0
            row = 16 * j + e
            for k in range(3 * m):
                s += Q[row, k] * p[k]
            A[e // 4, e % 4] = s
        top, second = _top_two(A, q)
        gap = min(gap, top - second)
        biggest = max(biggest, top)
        for a in range(4):
            for b in range(4):
                o[j, 4 * a + b] = q[a] * q[b]
    if not gap > 3.0 * degenerate * biggest:
        return DEGENERATE_TOP, R, t, o, p, cb
    rows = Zc.shape[1] // 3
    worst = 0.0
    for r in range(rows):
        d2 = 0.0
        for c in range(3):
            col = 3 * r + c
            s = 0.0
            for j in range(J):
                for e in range(16):
                    s += o[j, e] * Zc[16 * j + e, col]
            for k in range(3 * m):
                s += Lc[col, k] * p[k]
            d2 += s * s
        worst = max(worst, d2)
    if not math.sqrt(worst) <= limit:
        return FAILED, R, t, o, p, cb
    for a in range(3):
        for b in range(3):
            s = 0.0
            for e in range(16):
                s += o[0, e] * rotation_map[e, 3 * a + b]
            R[a, b] = s
    for a in range(3):
        t[a] = cb[a] - (R[a, 0] * cs[0, 0] + R[a, 1] * cs[0, 1] + R[a, 2] * cs[0, 2])
    return PASSED, R, t, o, p, cb


@numba.njit(cache=True, nogil=True)
def _kabsch(src, dst, w):
    """``solvers.rigid._kabsch_one``: weighted Kabsch by SVD with the reflection guard (Arun et al. 1987)."""
    m = src.shape[0]
    ws = 0.0
    for i in range(m):
        ws += w[i]
    if ws <= 0.0:
        return np.eye(3), np.zeros(3)
    cs = np.zeros(3)
    cd = np.zeros(3)
    for i in range(m):
        for c in range(3):
            cs[c] += w[i] * src[i, c]
            cd[c] += w[i] * dst[i, c]
    cs /= ws
    cd /= ws
    H = np.zeros((3, 3))
    for i in range(m):
        for a in range(3):
            for b in range(3):
                H[a, b] += (src[i, a] - cs[a]) * ((dst[i, b] - cd[b]) * w[i])
    U, _, Vt = np.linalg.svd(H)
    R = Vt.T @ U.T
    if np.linalg.det(R) < 0.0:
        for c in range(3):
            Vt[2, c] = -Vt[2, c]
        R = Vt.T @ U.T
    return R, cd - R @ cs


@numba.njit(cache=True, nogil=True)
def _half_median(r, lo, hi):
    srt = np.sort(r)
    return 0.5 * (srt[lo] + srt[hi])


@numba.njit(cache=True, nogil=True)
def refit(ref, P, o, p, cb, Wn, Z, cs, rotation_map, iterations, floor_mm, tukey_c, mad_to_sigma):
    """A frame that failed the check (``FrameFit.fit``): ``robust_pose``'s start, the leave-one-out fit whose
    median residual halves the plain fit's (scored from ``check_fit``'s ``o``, ``p``, ``cb`` and the prepared
    residual maps ``Z``), then IRLS with Tukey's biweight (Huber where Tukey keeps < 3) on the markers in use,
    ``ref`` and ``P`` (m, 3). Returns R, t and the markers' weights."""
    m = P.shape[0]
    J = Wn.shape[0]
    lo, hi = (m - 1) // 2, m // 2
    pc = p.reshape(m, 3)
    best = 0
    if J > 1:
        r = np.empty(m)
        low = np.inf
        for j in range(J):
            mean = np.zeros(3)
            for i in range(m):
                for c in range(3):
                    mean[c] += Wn[j, i] * pc[i, c]
            for i in range(m):
                d2 = 0.0
                for c in range(3):
                    s = 0.0
                    for e in range(16):
                        s += o[j, e] * Z[j, e, 3 * i + c]
                    s += mean[c] - pc[i, c]
                    d2 += s * s
                r[i] = math.sqrt(d2)
            score = _half_median(r, lo, hi)
            if j == 0:
                score *= 0.5
            if score < low:
                low, best = score, j
    R = np.zeros((3, 3))
    for a in range(3):
        for b in range(3):
            s = 0.0
            for e in range(16):
                s += o[best, e] * rotation_map[e, 3 * a + b]
            R[a, b] = s
    t = cb.copy()
    for c in range(3):
        for i in range(m):
            t[c] += Wn[best, i] * pc[i, c]
        t[c] -= R[c, 0] * cs[best, 0] + R[c, 1] * cs[best, 1] + R[c, 2] * cs[best, 2]
    w = np.ones(m)
    r = np.empty(m)
    u = np.empty(m)
    for _ in range(iterations):
        for i in range(m):
            d2 = 0.0
            for c in range(3):
                s = R[c, 0] * ref[i, 0] + R[c, 1] * ref[i, 1] + R[c, 2] * ref[i, 2] + t[c] - P[i, c]
                d2 += s * s
            r[i] = math.sqrt(d2)
        scale = max(mad_to_sigma * _half_median(r, lo, hi), floor_mm)
        kept = 0
        for i in range(m):
            u[i] = r[i] / (tukey_c * scale)
            w[i] = (1.0 - u[i] * u[i]) ** 2 if u[i] < 1.0 else 0.0
            if w[i] != 0.0:
                kept += 1
        if kept < 3:
            for i in range(m):
                w[i] = min(1.0, 1.0 / max(u[i], 1e-12))
        R, t = _kabsch(ref, P, w)
    return R, t, w


@numba.njit(cache=True, nogil=True)
def unrotate(positions, valid, R, t):
    """``(positions - t) @ R`` (R^T applied to each marker: head frame, Seol et al. 2012 §3.1), 0 where not
    ``valid``: the streamed frame's stabilised markers in one call instead of four array calls."""
    n = positions.shape[0]
    local = np.zeros((n, 3))
    for i in range(n):
        if valid[i]:
            x, y, z = positions[i, 0] - t[0], positions[i, 1] - t[1], positions[i, 2] - t[2]
            for c in range(3):
                local[i, c] = x * R[0, c] + y * R[1, c] + z * R[2, c]
    return local
