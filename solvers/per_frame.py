"""Per-frame baselines of Seol et al. 2012 §7 / Fig. 11, with missing markers' rows dropped.

* "No Const": unconstrained least squares min |B w - s|^2 per frame.
* "Range PF": the same with hard limits lower <= w <= upper (Bregler et al. 2002; Seol use
  -0.5 <= w <= 1.5), a box QP per frame solved with DAQP.
* "Prior PF": min |B w - s|^2 + alpha prior(w) per frame (Blanz and Vetter 1999), closed form.
"""

from __future__ import annotations

import daqp
import numpy as np

from solvers.prior import PCAPrior


def _masks(valid: np.ndarray):
    """Frames grouped by visibility pattern, so each distinct B_v^T B_v is formed once."""
    uniq, inv = np.unique(np.asarray(valid, dtype=bool), axis=0, return_inverse=True)
    return uniq, inv.reshape(-1)


def no_const(basis: np.ndarray, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
    return prior_pf(basis, targets, valid, None, 0.0)


def prior_pf(basis: np.ndarray, targets: np.ndarray, valid: np.ndarray, prior: PCAPrior | None,
             alpha: float) -> np.ndarray:
    """(B_v^T B_v + alpha P) w = B_v^T s_v + alpha P w_mean for every frame."""
    B = np.asarray(basis, dtype=np.float64)
    T, m = len(targets), B.shape[1]
    S = np.asarray(targets, dtype=np.float64).reshape(T, -1)
    uniq, inv = _masks(valid)
    W = np.zeros((T, m))
    P = alpha * prior.precision if prior is not None and alpha > 0 else np.zeros((m, m))
    c = P @ prior.mean_weights if prior is not None and alpha > 0 else np.zeros(m)
    for u, mask in enumerate(uniq):
        frames = np.flatnonzero(inv == u)
        rows = np.repeat(mask, 3)
        Bv = B[rows]
        A = Bv.T @ Bv + P
        rhs = S[np.ix_(frames, np.flatnonzero(rows))] @ Bv + c
        W[frames] = np.linalg.lstsq(A, rhs.T, rcond=None)[0].T
    return W


def range_pf(basis: np.ndarray, targets: np.ndarray, valid: np.ndarray, lower: np.ndarray | float,
             upper: np.ndarray | float) -> np.ndarray:
    """min |B_v w - s_v|^2 subject to lower <= w <= upper, per frame."""
    B = np.asarray(basis, dtype=np.float64)
    T, m = len(targets), B.shape[1]
    S = np.asarray(targets, dtype=np.float64).reshape(T, -1)
    lo = np.broadcast_to(np.asarray(lower, dtype=np.float64), (m,)).copy()
    hi = np.broadcast_to(np.asarray(upper, dtype=np.float64), (m,)).copy()
    uniq, inv = _masks(valid)
    A = np.zeros((0, m))
    W = np.zeros((T, m))
    for u, mask in enumerate(uniq):
        rows = np.repeat(mask, 3)
        Bv = B[rows]
        H = Bv.T @ Bv + 1e-9 * np.eye(m)
        for t in np.flatnonzero(inv == u):
            x, _, flag, _ = daqp.solve(H, -(Bv.T @ S[t, rows]), A, hi, lo)
            W[t] = x if flag >= 1 else np.clip(np.linalg.lstsq(Bv, S[t, rows], rcond=None)[0], lo, hi)
    return W
