"""Compiled (numba) Whittaker smoothing of gap windows (``solvers.whittaker.smooth``; the method is described there).

Why compiled: as whole-array numpy calls, the LDL' sweep over time cost ~15 calls a frame of the window, each on a
(tracks x candidates x axes) batch the candidates multiply ninefold; at 30 % of marker-frames missing that sweep was
most of a take's gap filling and most of what the occluded take costs beyond the clean one (issue 18,
docs/performance.md "Gap filling compiled"). Here each track sweeps its candidate smoothings side by side on one
(T, candidates, c) scratch and keeps only the best by GCV, so nothing is repeated ninefold in memory. The numbers
equal the numpy sweep's (tests/test_whittaker.py against tests/whittaker_reference.py). Kept apart from
``solvers.whittaker`` so that importing it (every CLI command does, through calibration) does not import numba.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, inline="always")
def _solve(d, e, f, w, lambdas, yw, D, L1, L2, x):
    """x (T, l, c) with (diag(w) + lambdas[l] D2'D2) x[:, l] = yw for every candidate l at once: LDL' without
    pivoting (each system is SPD), then back-substitution. The candidates are independent chains of divisions, so
    sweeping them side by side overlaps their latencies. ``d, e, f``: the penalty's bands; D, L1, L2 (T, l): scratch."""
    T, nl, c = x.shape
    for i in range(T):
        for li in range(nl):
            lam = lambdas[li]
            Di = d[i] * lam + w[i]
            if i >= 2:
                l2 = f[i - 2] * lam / D[i - 2, li]
                l1 = (e[i - 1] * lam - l2 * L1[i - 1, li] * D[i - 2, li]) / D[i - 1, li]
                Di -= l2 * l2 * D[i - 2, li]
                Di -= l1 * l1 * D[i - 1, li]
                for a in range(c):
                    x[i, li, a] = yw[i, a] - l2 * x[i - 2, li, a] - l1 * x[i - 1, li, a]
                L1[i, li], L2[i, li] = l1, l2
            elif i == 1:
                l1 = e[0] * lam / D[0, li]
                Di -= l1 * l1 * D[0, li]
                for a in range(c):
                    x[i, li, a] = yw[i, a] - l1 * x[i - 1, li, a]
                L1[i, li] = l1
            else:
                for a in range(c):
                    x[i, li, a] = yw[i, a]
            D[i, li] = Di
    for li in range(nl):
        for a in range(c):
            x[T - 1, li, a] /= D[T - 1, li]
    for i in range(T - 2, -1, -1):
        for li in range(nl):
            for a in range(c):
                v = x[i, li, a] / D[i, li] - L1[i + 1, li] * x[i + 1, li, a]
                if i + 2 < T:
                    v -= L2[i + 2, li] * x[i + 2, li, a]
                x[i, li, a] = v


@numba.njit(cache=True, nogil=True)
def smooth_tracks(y, seen, d, e, f, lambdas, dof_fraction):
    """Smoothed tracks (k, T, c) of ``y`` (k, T, c: track-major, each track's frames contiguous) seen where ``seen``
    (k, T), each with the candidate of ``lambdas`` of least GCV score (first on ties), and that candidate's index."""
    k, T, c = y.shape
    nl = len(lambdas)
    out = np.empty_like(y)
    best = np.zeros(k, dtype=np.int64)
    yw, x = np.empty((T, c)), np.empty((T, nl, c))
    w = np.empty(T)
    D, L1, L2 = np.empty((T, nl)), np.zeros((T, nl)), np.zeros((T, nl))
    rss = np.empty(nl)
    for j in range(k):
        yj, sj = y[j], seen[j]
        n = 0.0
        for i in range(T):
            w[i] = 1.0 if sj[i] else 0.0
            n += w[i]
            for a in range(c):
                yw[i, a] = yj[i, a] if sj[i] else 0.0
        _solve(d, e, f, w, lambdas, yw, D, L1, L2, x)
        rss[:] = 0.0
        for i in range(T):
            if sj[i]:
                for li in range(nl):
                    for a in range(c):
                        r = x[i, li, a] - yj[i, a]
                        rss[li] += r * r
        best_score = np.inf
        for li in range(nl):
            dof = max(n * dof_fraction[li], 2.0)
            score = rss[li] / max(n - dof, 1e-9) ** 2
            if score < best_score:
                best_score = score
                best[j] = li
        for i in range(T):
            for a in range(c):
                out[j, i, a] = x[i, best[j], a]
    return out, best
