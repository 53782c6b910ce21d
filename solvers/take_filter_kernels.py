"""Compiled (numba) whole-take causal polynomial filter (``solvers.take_filters.causal_poly_take``).

Why compiled: at real occlusion a sixth of a take's (frame, channel) windows are partly missing, and each
is its own weighted least-squares fit; as numpy batches (index arrays, einsums, a batched ``solve``)
they cost more than the rest of the robust mode's whole-take solve (docs/performance.md, "Whole takes").
Here one pass per channel keeps a running count of seen samples and fits a partial window in registers.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _fit_newest(x, ok, t, W, V, G, r):
    """The weighted least-squares polynomial through the seen samples of window ``t - W + 1 .. t`` of one
    channel ``x``, evaluated at ``t``: the normal equations ``V' D V c = V' D x`` solved by Gaussian
    elimination with partial pivoting, as the stream's ``np.linalg.solve`` (LAPACK getrf) does; Cholesky
    lost ~7x more digits on three samples far back in a long window."""
    p = V.shape[1]
    G[:, :] = 0.0
    r[:] = 0.0
    for k in range(W):
        row = t - W + 1 + k
        if row >= 0 and ok[row]:
            for i in range(p):
                vi = V[k, i]
                r[i] += vi * x[row]
                for j in range(p):
                    G[i, j] += vi * V[k, j]
    for j in range(p):
        piv = j
        for i in range(j + 1, p):
            if abs(G[i, j]) > abs(G[piv, j]):
                piv = i
        if piv != j:
            for k in range(p):
                G[j, k], G[piv, k] = G[piv, k], G[j, k]
            r[j], r[piv] = r[piv], r[j]
        for i in range(j + 1, p):
            f = G[i, j] / G[j, j]
            for k in range(j + 1, p):
                G[i, k] -= f * G[j, k]
            r[i] -= f * r[j]
    for i in range(p - 1, -1, -1):
        s = r[i]
        for k in range(i + 1, p):
            s -= G[i, k] * r[k]
        r[i] = s / G[i, i]
    y = 0.0
    for i in range(p):
        y += r[i] * V[W - 1, i]
    return y


@numba.njit(cache=True, nogil=True)
def causal_poly_channels(x, ok, h, V, out):
    """``out`` (C, T) = the causal end-point filter of each channel of ``x`` (C, T) seen where ``ok`` (C, T):
    the fixed weights ``h`` where the whole window is seen, the weighted fit where more than ``order`` samples
    are, else the newest seen sample, else (missing) the output at the channel's last seen frame (0 before any).
    The stream's start counts as missing samples."""
    C, T = x.shape
    W = len(h)
    p = V.shape[1]
    G = np.empty((p, p))
    r = np.empty(p)
    for c in range(C):
        xc, okc, oc = x[c], ok[c], out[c]
        count = 0
        last = 0.0
        for t in range(T):
            if okc[t]:
                count += 1
            if t >= W and okc[t - W]:
                count -= 1
            if count == W:
                y = 0.0
                for k in range(W):
                    y += h[k] * xc[t - W + 1 + k]
            elif count >= p:
                y = _fit_newest(xc, okc, t, W, V, G, r)
            elif okc[t]:
                y = xc[t]
            else:
                y = last
            oc[t] = y
            if okc[t]:
                last = y


@numba.njit(cache=True, nogil=True)
def causal_poly_frame(ring, ring_ok, start, h, V, flat, okf, last, out):
    """One streamed frame of the same filter (``solvers.filters.CausalPolyFilter.step``): channel ``c``'s window
    is ``ring[start:start + W, c]`` (oldest .. newest, the newest being ``flat``), seen where ``ring_ok``; the
    same cases as ``causal_poly_channels``, then ``last`` (the output at each channel's last seen frame) is
    updated in place. Compiled because at real occlusion most frames have a partly missing window, whose
    numpy batch (two einsums and a batched solve) cost more than the robust mode's QP (docs/performance.md)."""
    W = len(h)
    p = V.shape[1]
    G = np.empty((p, p))
    r = np.empty(p)
    t = start + W - 1
    for c in range(flat.size):
        count = 0
        for k in range(W):
            if ring_ok[start + k, c]:
                count += 1
        if count == W:
            y = 0.0
            for k in range(W):
                y += h[k] * ring[start + k, c]
        elif count >= p:
            y = _fit_newest(ring[:, c], ring_ok[:, c], t, W, V, G, r)
        elif okf[c]:
            y = flat[c]
        else:
            y = last[c]
        out[c] = y
        if okf[c]:
            last[c] = y
