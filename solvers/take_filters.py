"""Whole-take forms of the streaming filters: the same numbers as stepping them frame by frame.

The causal quadratic end-point filter (``solvers.filters.CausalPolyFilter``; the causal end of a
Savitzky-Golay fit, Savitzky & Golay 1964) is linear where its window is fully visible: an FIR
over the time axis, so a take is one sum of ``window`` shifted copies instead of T Python steps.
Where markers are missing it fits a weighted quadratic per (frame, channel); those fits are solved
as one batch of 3 x 3 systems, and channels with too few samples hold their last output, as the
stream does.
"""

from __future__ import annotations

import numpy as np

from solvers.filters import endpoint_weights


def causal_poly_take(X: np.ndarray, valid: np.ndarray | None, window: int, order: int = 2) -> np.ndarray:
    """``CausalPolyFilter(window, order).filter(X, valid)`` without the per-frame loop.

    ``X`` is (T, ...) and ``valid`` None or broadcastable to it; the stream's start (an empty
    window) counts as missing samples, exactly as its zero-initialised ring does.
    """
    X = np.asarray(X, dtype=np.float64)
    T = len(X)
    if T == 0:
        return X.copy()
    flat = X.reshape(T, -1)
    ok = (np.ones(flat.shape, bool) if valid is None
          else np.broadcast_to(np.asarray(valid, bool), X.shape).reshape(T, -1))
    W = int(window)
    h = endpoint_weights(W, order)
    seen = np.cumsum(ok, axis=0, dtype=np.int64)
    count = seen.copy()
    count[W:] -= seen[:-W]
    full = count == W
    out = np.where(ok, flat, 0.0)
    if T >= W:
        fir = h[0] * flat[:T - W + 1]
        for k in range(1, W):
            fir += h[k] * flat[k:T - W + 1 + k]
        out[W - 1:] = np.where(full[W - 1:], fir, out[W - 1:])
    part = ~full & (count > order)
    if part.any():
        t, c = np.nonzero(part)
        lags = np.arange(-(W - 1), 1)
        rows = t[:, None] + lags  # (P, W) frames of each window, oldest .. newest
        inside = rows >= 0
        at = np.maximum(rows, 0)
        w = (ok[at, c[:, None]] & inside).astype(np.float64)
        V = np.vander(lags.astype(np.float64), order + 1, increasing=True)
        G = np.einsum("pw,wi,wj->pij", w, V, V)
        r = np.einsum("pw,wi,pw->pi", w, V, np.where(inside, flat[at, c[:, None]], 0.0))
        coef = np.linalg.solve(G, r[..., None])[..., 0]
        out[t, c] = coef @ V[-1]
    hold = ~ok & ~part
    if hold.any():
        frames = np.where(ok, np.arange(T)[:, None], -1)
        last = np.maximum.accumulate(frames, axis=0)
        held = np.where(last >= 0, out[np.maximum(last, 0), np.arange(flat.shape[1])], 0.0)
        out = np.where(hold, held, out)
    return out.reshape(X.shape)
