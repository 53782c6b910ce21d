"""The whole-array numpy Whittaker smoother (solvers/whittaker.py before its sweep was compiled, 56fe5c0): the
reference that ``solvers.whittaker_kernels`` is tested against (tests/test_whittaker.py)."""

from __future__ import annotations

import numpy as np

from solvers.whittaker import _DOF_FRACTION, LAMBDAS, _penalty_bands


def solve_pentadiagonal(d: np.ndarray, e: np.ndarray, f: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x with A x = b for a batch of symmetric positive definite pentadiagonal A.

    ``d`` (T, B) diagonal, ``e`` (T-1, B) and ``f`` (T-2, B) first and second off-diagonals,
    ``b`` (T, B, c). LDL' without pivoting (A is SPD), time-major so each step is one row."""
    T = len(d)
    D = np.empty_like(d)
    L1 = np.zeros_like(d)  # L[i, i-1]
    L2 = np.zeros_like(d)  # L[i, i-2]
    z = np.empty_like(b)
    for i in range(T):
        Di = d[i].copy()
        zi = b[i].copy()
        if i >= 1:
            if i >= 2:
                L2[i] = f[i - 2] / D[i - 2]
                L1[i] = (e[i - 1] - L2[i] * L1[i - 1] * D[i - 2]) / D[i - 1]
                Di -= L2[i] * L2[i] * D[i - 2]
                zi -= L2[i][:, None] * z[i - 2]
            else:
                L1[i] = e[0] / D[0]
            Di -= L1[i] * L1[i] * D[i - 1]
            zi -= L1[i][:, None] * z[i - 1]
        D[i] = Di
        z[i] = zi
    x = z / D[..., None]
    for i in range(T - 2, -1, -1):
        x[i] -= L1[i + 1][:, None] * x[i + 1]
        if i + 2 < T:
            x[i] -= L2[i + 2][:, None] * x[i + 2]
    return x


def numpy_smooth(y: np.ndarray, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T, k, c = y.shape
    nl = len(LAMBDAS)
    w = seen.astype(np.float64)
    pd, pe, pf = _penalty_bands(T)
    lam = np.tile(LAMBDAS, k)  # batch index = track * nl + candidate
    d = pd[:, None] * lam + np.repeat(w, nl, axis=1)
    e = pe[:, None] * lam
    f = pf[:, None] * lam
    rhs = np.repeat(np.where(seen[..., None], y, 0.0), nl, axis=1)
    x = solve_pentadiagonal(d, e, f, rhs).reshape(T, k, nl, c)
    resid = np.where(seen[:, :, None, None], x - y[:, :, None, :], 0.0)
    rss = np.einsum("tklc,tklc->kl", resid, resid)
    n = seen.sum(axis=0).astype(np.float64)
    dof = np.maximum(n[:, None] * _DOF_FRACTION[None, :], 2.0)
    score = rss / np.maximum(n[:, None] - dof, 1e-9) ** 2
    best = np.argmin(score, axis=1)
    return x[:, np.arange(k), best], LAMBDAS[best]
