"""Whole-take forms of the streaming filters: the same numbers as stepping them frame by frame.

The causal quadratic end-point filter (``solvers.filters.CausalPolyFilter``; the causal end of a
Savitzky-Golay fit, Savitzky & Golay 1964) is linear where its window is fully visible: an FIR
over the time axis. Where markers are missing it fits a weighted quadratic per (frame, channel),
and channels with too few samples hold their last output, as the stream does. A take is one
compiled pass per channel instead of T Python steps.
"""

from __future__ import annotations

import numpy as np

from solvers.filters import endpoint_weights


def causal_poly_take(X: np.ndarray, valid: np.ndarray | None, window: int, order: int = 2) -> np.ndarray:
    """``CausalPolyFilter(window, order).filter(X, valid)`` without the per-frame loop.

    ``X`` is (T, ...) and ``valid`` None or broadcastable to it; the stream's start (an empty
    window) counts as missing samples, exactly as its zero-initialised ring does. One compiled pass per
    channel (``solvers.take_filter_kernels``, imported here so that importing this module does not import numba).
    """
    from solvers.take_filter_kernels import causal_poly_channels

    X = np.asarray(X, dtype=np.float64)
    T = len(X)
    if T == 0:
        return X.copy()
    ok = (np.ones(X.shape, bool) if valid is None
          else np.broadcast_to(np.asarray(valid, bool), X.shape))
    x = np.ascontiguousarray(X.reshape(T, -1).T)  # channel-major: a channel's frames contiguous
    okc = np.ascontiguousarray(ok.reshape(T, -1).T)
    W = int(window)
    V = np.vander(np.arange(-(W - 1), 1, dtype=np.float64), int(order) + 1, increasing=True)
    out = np.empty_like(x)
    causal_poly_channels(x, okc, endpoint_weights(W, order), V, out)
    return np.ascontiguousarray(out.T).reshape(X.shape)
