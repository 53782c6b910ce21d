"""The streamed head fit's check in numpy (``FrameFit.fit`` before it was compiled, 56fe5c0): the reference that
``solvers.rigid_kernels.check_fit`` is tested against (tests/test_stabilise.py)."""

from __future__ import annotations

import math

import numpy as np

from livecap.calibration.stabilise import CHECK_SCALES
from solvers.rigid import DEGENERATE, ROTATION_MAP
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
