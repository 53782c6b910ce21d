"""Compiled (numba) forward passes of the offline marker smoother (``solvers.marker_kalman.smooth_take``).

Why compiled: ``smooth_take`` runs a bank of constant-velocity filters over every frame of a take three times (the
shared r's choice over the whole (r, q) grid, the local q choice, then the chosen filter recorded for the
Rauch-Tung-Striebel pass; Bar-Shalom, Li & Kirubarajan 2001 §6.2.2). As whole-array numpy calls that was ~40 calls
a frame on arrays of up to 105 filters x n markers x 3: 3.7 s of the 5.0 s `kalman` took over a 30 s ICT take
(issue 18, docs/performance.md "The offline marker smoother compiled"). Here one loop over frames, filters and
markers does the same arithmetic in the same order; only ``log`` may differ from numpy's in the last bit.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def bank_take(z, seen, r, q, p11_start, ll, h, best, xs, ps, xp, pp):
    """K filters (rows of ``r`` (K, n)) over the take ``z`` (T, n, 3) seen where ``seen`` (T, n); frame t > 0 is
    predicted with ``q[min(t, len(q) - 1)]`` (q: (Tq, K, n)). A marker's first sighting starts its filters there
    (velocity unknown, velocity variance ``p11_start``). Outputs, each skipped when given empty:
    ``ll`` (K, n, 3) += every frame's innovation log-likelihoods; ``best`` (T, n) per frame and marker the filter
    whose log-likelihood, coordinates summed, is largest over frames t - ``h`` .. t + ``h`` (clipped to the take;
    the first on a tie, as numpy's argmax); for K = 1 the filtered (``xs`` (T, 2, 3n), ``ps`` (T, 3, n)) and
    predicted (``xp``, ``pp``) states, as (value, velocity) and (p00, p01, p11).

    ``best`` is read off running sums over frames, ``cum[u]`` of frames before u, as the difference
    ``cum[min(t + h + 1, T)] - cum[max(t - h, 0)]``; only their last 2h + 2 rows are kept (a ring), and frame t's
    choice is made once frame t + h is filtered (issue 39 item 2: the sums of every frame as a T + 1 x K x n array
    and the choice in numpy were ~17 ms of a 30 s ICT take's ~57 ms smoother pass)."""
    T, n, _ = z.shape
    K = r.shape[0]
    x, v = np.zeros((K, n, 3)), np.zeros((K, n, 3))
    p00, p01, p11 = np.full((K, n), 1e6), np.zeros((K, n)), np.full((K, n), p11_start)
    started = np.zeros(n, dtype=np.bool_)
    want_ll, want_cum, record = ll.size > 0, best.size > 0, xs.size > 0
    W = 2 * h + 2
    cum = np.zeros((W if want_cum else 0, K, n))
    Tq = q.shape[0]
    for t in range(T):
        qt = q[min(t, Tq - 1)]
        now, nxt = t % W, (t + 1) % W  # cum[t] and cum[t + 1] in the ring
        if want_cum:
            cum[nxt] = cum[now]
        for k in range(K):
            last_s, last_log = np.nan, 0.0  # markers seen alike have equal covariances: one log for them
            ca = cb = cd = cw = cr = np.nan  # the last predict-and-correct's inputs: equal ones reuse its numbers
            P00 = P01 = P11 = s = k0 = k1 = n00 = n01 = n11 = 0.0
            for i in range(n):
                if t and seen[t, i] and started[i]:  # the common case, its covariance arithmetic shared
                    a, b, d, w, rr = p00[k, i], p01[k, i], p11[k, i], qt[k, i], r[k, i]
                    if not (a == ca and b == cb and d == cd and w == cw and rr == cr):
                        ca, cb, cd, cw, cr = a, b, d, w, rr
                        P00, P01, P11 = a + 2 * b + d + w / 3, b + d + w / 2, d + w
                        s = P00 + rr
                        k0, k1 = P00 / s, P01 / s
                        if s != last_s:
                            last_s, last_log = s, math.log(s)
                        n00, n01, n11 = P00 - k0 * P00, P01 - k0 * P01, P11 - k1 * P01
                    frame = 0.0
                    for c in range(3):
                        xc = x[k, i, c] + v[k, i, c]
                        if record:
                            xp[t, 0, 3 * i + c], xp[t, 1, 3 * i + c] = xc, v[k, i, c]
                        e = z[t, i, c] - xc
                        x[k, i, c] = xc + k0 * e
                        v[k, i, c] = v[k, i, c] + k1 * e
                        like = -0.5 * (last_log + e * e / s)
                        if want_ll:
                            ll[k, i, c] += like
                        frame += like
                    if want_cum:
                        cum[nxt, k, i] = cum[now, k, i] + frame
                    if record:
                        pp[t, 0, i], pp[t, 1, i], pp[t, 2, i] = P00, P01, P11
                    p00[k, i], p01[k, i], p11[k, i] = n00, n01, n11
                    if record:
                        for c in range(3):
                            xs[t, 0, 3 * i + c], xs[t, 1, 3 * i + c] = x[k, i, c], v[k, i, c]
                        ps[t, 0, i], ps[t, 1, i], ps[t, 2, i] = n00, n01, n11
                    continue
                if t:
                    for c in range(3):
                        x[k, i, c] = x[k, i, c] + v[k, i, c]
                    a, b, d, w = p00[k, i], p01[k, i], p11[k, i], qt[k, i]
                    p00[k, i] = a + 2 * b + d + w / 3
                    p01[k, i] = b + d + w / 2
                    p11[k, i] = d + w
                if record:
                    for c in range(3):
                        xp[t, 0, 3 * i + c], xp[t, 1, 3 * i + c] = x[k, i, c], v[k, i, c]
                    pp[t, 0, i], pp[t, 1, i], pp[t, 2, i] = p00[k, i], p01[k, i], p11[k, i]
                if seen[t, i]:  # a first sighting (a seen, started marker took the path above)
                    for c in range(3):
                        x[k, i, c], v[k, i, c] = z[t, i, c], 0.0
                    p00[k, i], p01[k, i], p11[k, i] = r[k, i], 0.0, p11_start
                if record:
                    for c in range(3):
                        xs[t, 0, 3 * i + c], xs[t, 1, 3 * i + c] = x[k, i, c], v[k, i, c]
                    ps[t, 0, i], ps[t, 1, i], ps[t, 2, i] = p00[k, i], p01[k, i], p11[k, i]
        for i in range(n):
            if seen[t, i]:
                started[i] = True
        if want_cum:  # the frames whose window ends with this one: t - h, and at the take's end every one left
            for u in range(max(t - h, 0), t + 1 if t == T - 1 else t - h + 1):
                _local_best(cum, nxt, max(u - h, 0) % W, best[u])


@numba.njit(cache=True, nogil=True, inline="always")
def _local_best(cum, end, start, out):
    """Per marker, the first filter of the largest ``cum[end] - cum[start]`` (a NaN counts as largest, as in
    numpy's argmax)."""
    K, n = cum.shape[1], cum.shape[2]
    for i in range(n):
        top, at = cum[end, 0, i] - cum[start, 0, i], 0
        if not math.isnan(top):
            for k in range(1, K):
                d = cum[end, k, i] - cum[start, k, i]
                if d > top or math.isnan(d):
                    top, at = d, k
                    if math.isnan(d):
                        break
        out[i] = at


@numba.njit(cache=True, nogil=True)
def rts(xs, ps, xp, pp, out):
    """Rauch-Tung-Striebel backward pass into ``out`` (T, 3n) over filtered (``xs`` (T, 2, 3n), ``ps`` (T, 3, n))
    and predicted (``xp``, ``pp``) states, a marker's covariances shared by its three coordinates: the arithmetic
    of ``solvers.marker_kalman._rts`` (its numpy reference) element by element, without its ~20 array calls a
    frame and the covariances repeated per coordinate (docs/performance.md, "`kalman` against `robust`")."""
    T, _, C = xs.shape
    x, v = xs[T - 1, 0].copy(), xs[T - 1, 1].copy()
    out[T - 1] = x
    for t in range(T - 2, -1, -1):
        for c in range(C):
            i = c // 3
            f00, f01, f11 = ps[t, 0, i], ps[t, 1, i], ps[t, 2, i]
            a00, a01, a11 = pp[t + 1, 0, i], pp[t + 1, 1, i], pp[t + 1, 2, i]
            det = a00 * a11 - a01 * a01
            i00, i01, i11 = a11 / det, -a01 / det, a00 / det
            b00, b01, b10, b11 = f00 + f01, f01, f01 + f11, f11
            j00, j01 = b00 * i00 + b01 * i01, b00 * i01 + b01 * i11
            j10, j11 = b10 * i00 + b11 * i01, b10 * i01 + b11 * i11
            dx, dv = x[c] - xp[t + 1, 0, c], v[c] - xp[t + 1, 1, c]
            x[c] = xs[t, 0, c] + j00 * dx + j01 * dv
            v[c] = xs[t, 1, c] + j10 * dx + j11 * dv
            out[t, c] = x[c]
