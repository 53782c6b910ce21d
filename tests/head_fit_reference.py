"""The streamed head fit's check in numpy (``FrameFit.fit`` before it was compiled, 56fe5c0): the reference that
``solvers.rigid_kernels.check_fit`` is tested against (tests/test_stabilise.py)."""

from __future__ import annotations

import math

import numpy as np

from livecap.calibration.stabilise import CHECK_SCALES, MAD_TO_SIGMA, TUKEY_C
from solvers.rigid import DEGENERATE, ROTATION_MAP, kabsch
from solvers.rigid_kernels import DEGENERATE_TOP, FAILED, PASSED


def check_fit(P, Wn, Q, Zc, Lc, cs, floor_mm=1.0):
    """(outcome, R, t, o, p, cb) as ``rigid_kernels.check_fit``; R, t only when the check passes."""
    J = len(Wn)
    cb = Wn[0] @ P
    p = (P - cb).reshape(-1)
    ev, V = np.linalg.eigh((Q @ p).reshape(J, 4, 4))
    top = ev[:, 3]
    q = V[:, :, 3]
    o = np.einsum("ji,jk->jik", q, q).reshape(J, 16)
    if not (top - ev[:, 2]).min() > 3.0 * DEGENERATE * top.max():
        return DEGENERATE_TOP, None, None, o, p, cb
    d = (o.reshape(-1) @ Zc + Lc @ p).reshape(-1, 3)
    if not math.sqrt(np.einsum("ic,ic->i", d, d).max()) <= CHECK_SCALES * floor_mm:
        return FAILED, None, None, o, p, cb
    R0 = (o[0] @ ROTATION_MAP).reshape(3, 3)
    return PASSED, R0, cb - R0 @ cs[0], o, p, cb


def refit(ref, P, o, p, cb, Wn, Z, cs, iterations=3, floor_mm=1.0):
    """``rigid_kernels.refit``: the best leave-one-out start, then IRLS on the markers in use."""
    J, m = len(Wn), len(P)
    b = 0
    if J > 1:
        pc = p.reshape(m, 3)
        d = np.matmul(o[:, None], Z).reshape(J, m, 3) + (Wn @ pc)[:, None] - pc
        srt = np.sort(np.sqrt(np.einsum("jic,jic->ji", d, d)), axis=1)
        score = 0.5 * (srt[:, (m - 1) // 2] + srt[:, m // 2])
        score[0] *= 0.5
        b = int(np.argmin(score))
    R = (o[b] @ ROTATION_MAP).reshape(3, 3)
    t = cb + Wn[b] @ p.reshape(m, 3) - R @ cs[b]
    return _irls_one(ref, P, R, t, iterations, floor_mm)


def _irls_one(ref, pts, R, t, iterations, floor_mm):
    """``_irls``'s iterations for one frame's markers in use, from the start ``R``, ``t``."""
    m = len(ref)
    lo, hi = (m - 1) // 2, m // 2
    w = np.ones(m)
    for _ in range(iterations):
        d = ref @ R.T + t - pts
        r = np.sqrt(np.einsum("ic,ic->i", d, d))
        srt = np.sort(r).tolist()
        u = r / (TUKEY_C * max(MAD_TO_SIGMA * (0.5 * (srt[lo] + srt[hi])), floor_mm))
        w = 1.0 - u * u
        w *= w
        w[u >= 1.0] = 0.0
        if np.count_nonzero(w) < 3:
            w = np.minimum(1.0, 1.0 / np.maximum(u, 1e-12))
        R, t = kabsch(ref, pts, w)
    return R, t, w
