"""Compiled (numba) rigid fits of a whole take with each marker left out in turn
(``livecap.calibration.stabilise._fit_with_deleted``, the robust head fit's check over a take).

Why compiled: per frame the check is the plain fit and, for 5-12 stable markers, the k leave-one-out fits (Horn 1987
§4: each rotation the top eigenvector of a symmetric 4 x 4 matrix N, its eigenvalue by Newton's method on N's
characteristic quartic from the upper bound, Theobald 2005 Eqs. 5-10; the eigenvector a column of the adjugate of
N - lambda I), then every marker's residual and deleted residual. As numpy batches over a 30 s take these were
~20 ms of array passes; here one pass per frame keeps a fit in registers. Results equal the numpy form to rounding;
a fit whose top eigenvalue is not simple (or whose Newton iteration did not settle) is flagged, and its frame is
redone by the numpy form (which takes those fits from the SVD).
"""

from __future__ import annotations

import math

import numba
import numpy as np

NEWTON_MAX = 12  # as solvers.rigid


@numba.njit(cache=True, nogil=True, inline="always")
def _adjugate4(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, adj):
    """Adjugate of a symmetric 4 x 4 from 2 x 2 minors (``solvers.rigid._adjugate4``) into ``adj``; returns the
    determinant."""
    a10, a20, a30, a21, a31, a32 = a01, a02, a03, a12, a13, a23
    s0 = a00 * a11 - a10 * a01
    s1 = a00 * a12 - a10 * a02
    s2 = a00 * a13 - a10 * a03
    s3 = a01 * a12 - a11 * a02
    s4 = a01 * a13 - a11 * a03
    s5 = a02 * a13 - a12 * a03
    c5 = a22 * a33 - a32 * a23
    c4 = a21 * a33 - a31 * a23
    c3 = a21 * a32 - a31 * a22
    c2 = a20 * a33 - a30 * a23
    c1 = a20 * a32 - a30 * a22
    c0 = a20 * a31 - a30 * a21
    adj[0, 0] = a11 * c5 - a12 * c4 + a13 * c3
    adj[0, 1] = -a01 * c5 + a02 * c4 - a03 * c3
    adj[0, 2] = a31 * s5 - a32 * s4 + a33 * s3
    adj[0, 3] = -a21 * s5 + a22 * s4 - a23 * s3
    adj[1, 0] = -a10 * c5 + a12 * c2 - a13 * c1
    adj[1, 1] = a00 * c5 - a02 * c2 + a03 * c1
    adj[1, 2] = -a30 * s5 + a32 * s2 - a33 * s1
    adj[1, 3] = a20 * s5 - a22 * s2 + a23 * s1
    adj[2, 0] = a10 * c4 - a11 * c2 + a13 * c0
    adj[2, 1] = -a00 * c4 + a01 * c2 - a03 * c0
    adj[2, 2] = a30 * s4 - a31 * s2 + a33 * s0
    adj[2, 3] = -a20 * s4 + a21 * s2 - a23 * s0
    adj[3, 0] = -a10 * c3 + a11 * c1 - a12 * c0
    adj[3, 1] = a00 * c3 - a01 * c1 + a02 * c0
    adj[3, 2] = -a30 * s3 + a31 * s1 - a32 * s0
    adj[3, 3] = a20 * s3 - a21 * s1 + a22 * s0
    return s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0


@numba.njit(cache=True, nogil=True)
def _rotation(H, bound, degenerate, R, adj):
    """The Kabsch rotation of the cross-covariance ``H`` (3 x 3) into ``R``; False where the top eigenvalue of Horn's
    N is not simple or Newton's method did not settle (``solvers.rigid._rotation_newton`` for one fit)."""
    sxx, sxy, sxz = H[0, 0], H[0, 1], H[0, 2]
    syx, syy, syz = H[1, 0], H[1, 1], H[1, 2]
    szx, szy, szz = H[2, 0], H[2, 1], H[2, 2]
    n00, n11, n22, n33 = sxx + syy + szz, sxx - syy - szz, syy - sxx - szz, szz - sxx - syy
    n01, n02, n03 = syz - szy, szx - sxz, sxy - syx
    n12, n13, n23 = sxy + syx, szx + sxz, syz + szy
    c2 = 0.0
    for a in range(3):
        for b in range(3):
            c2 += H[a, b] * H[a, b]
    c2 *= -2.0
    c1 = -8.0 * (sxx * (syy * szz - syz * szy) - sxy * (syx * szz - syz * szx) + sxz * (syx * szy - syy * szx))
    c0 = _adjugate4(n00, n01, n02, n03, n11, n12, n13, n22, n23, n33, adj)
    lam = bound
    moving = True
    for _ in range(NEWTON_MAX):
        lam2 = lam * lam
        p = (lam2 + c2) * lam2 + c1 * lam + c0
        dp = 4.0 * lam2 * lam + 2.0 * c2 * lam + c1
        step = p / dp if dp > 0 else 0.0
        lam -= step
        moving = abs(step) > 1e-14 * abs(lam)
        if not moving:
            break
    _adjugate4(n00 - lam, n01, n02, n03, n11 - lam, n12, n13, n22 - lam, n23, n33 - lam, adj)
    best, top = 0, -adj[0, 0]  # adj = (product of 3 negative gaps) q q^T: its most negative diagonal picks q
    for c in range(1, 4):
        if -adj[c, c] > top:
            best, top = c, -adj[c, c]
    w, x, y, z = adj[0, best], adj[1, best], adj[2, best], adj[3, best]
    norm = math.sqrt(max(w * w + x * x + y * y + z * z, 1e-300))
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    R[0, 0], R[0, 1], R[0, 2] = w * w + x * x - y * y - z * z, 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)
    R[1, 0], R[1, 1], R[1, 2] = 2.0 * (x * y + w * z), w * w - x * x + y * y - z * z, 2.0 * (y * z - w * x)
    R[2, 0], R[2, 1], R[2, 2] = 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), w * w - x * x - y * y + z * z
    scale = max(abs(lam), math.sqrt(max(-0.5 * c2, 0.0)))
    return not moving and top > degenerate * scale ** 3


@numba.njit(cache=True, nogil=True)
def fit_with_deleted_take(ref, pts, use, loo, degenerate, R_all, t_all, r_out):
    """Per frame of ``pts`` (T, k, 3) seen where ``use`` (T, k): the plain fit ``R ref + t ~ pts`` and, with ``loo``,
    the fit leaving out each marker (``R_all`` (T, J, 3, 3), ``t_all`` (T, J, 3)), and each marker's residual, the
    larger of it and its deleted residual where 4 or more markers are left (``r_out``). Returns the frames with a
    fit to redo (see the module's doc)."""
    T, k = use.shape
    J = R_all.shape[1]
    redo = np.zeros(T, np.bool_)
    a = np.empty((k, 3))
    b = np.empty((k, 3))
    cs = np.empty((J, 3))
    cd = np.empty((J, 3))
    wsum = np.empty(J)
    H = np.empty((3, 3))
    R = np.empty((3, 3))
    adj = np.empty((4, 4))
    for f in range(T):
        n0 = 0.0
        ca = np.zeros(3)
        cb = np.zeros(3)
        for i in range(k):
            if use[f, i]:
                n0 += 1.0
                for c in range(3):
                    ca[c] += ref[i, c]
                    cb[c] += pts[f, i, c]
        n0 = max(n0, 1e-300)
        for c in range(3):
            ca[c] /= n0
            cb[c] /= n0
        for i in range(k):
            for c in range(3):
                a[i, c] = ref[i, c] - ca[c]
                b[i, c] = pts[f, i, c] - cb[c]
        for j in range(J):
            ws, sq = 0.0, 0.0
            sa = np.zeros(3)
            sb = np.zeros(3)
            H[:, :] = 0.0
            for i in range(k):
                if use[f, i] and i != j - 1:
                    ws += 1.0
                    for c in range(3):
                        sa[c] += a[i, c]
                        sb[c] += b[i, c]
                        sq += a[i, c] * a[i, c] + b[i, c] * b[i, c]
                        for e in range(3):
                            H[c, e] += a[i, c] * b[i, e]
            inv = 1.0 / max(ws, 1e-300)
            wsum[j] = ws
            norms = 0.0
            for c in range(3):
                cs[j, c] = sa[c] * inv
                cd[j, c] = sb[c] * inv
                norms += cs[j, c] * cs[j, c] + cd[j, c] * cd[j, c]
            for c in range(3):
                for e in range(3):
                    H[c, e] -= ws * cs[j, c] * cd[j, e]
            if not _rotation(H, 0.5 * (sq - ws * norms), degenerate, R, adj):
                redo[f] = True
            for c in range(3):
                s = cb[c] + cd[j, c]
                for e in range(3):
                    R_all[f, j, c, e] = R[c, e]
                    s -= R[c, e] * (ca[e] + cs[j, e])
                t_all[f, j, c] = s
        for i in range(k):
            d2 = 0.0
            for c in range(3):
                s = cd[0, c] - b[i, c]
                for e in range(3):
                    s += R_all[f, 0, c, e] * (a[i, e] - cs[0, e])
                d2 += s * s
            r = math.sqrt(d2)
            if loo and use[f, i] and wsum[i + 1] >= 4:
                d2 = 0.0
                for c in range(3):
                    s = cd[i + 1, c] - b[i, c]
                    for e in range(3):
                        s += R_all[f, i + 1, c, e] * (a[i, e] - cs[i + 1, e])
                    d2 += s * s
                r = max(r, math.sqrt(d2))
            r_out[f, i] = r
    return redo
