"""Compiled (numba) frame step of the streaming marker filter bank (``solvers.marker_kalman.StreamingMarkerKalman``).

Why compiled: a frame is 21 constant-velocity filters (the lambda = q / r bank) over every marker's three
coordinates, the discounted likelihood sums, the choice of the shared r and of each marker's filter, and the
one-frame fixed-lag smoothing step (Bar-Shalom, Li & Kirubarajan 2001 §6.2.2 for the filter). As whole-array
numpy calls it was ~60 calls a frame on arrays of a few thousand numbers: 150-220 µs a frame at 72 markers
(docs/performance.md, "kalman's streamed step"); here one loop over markers and filters.

The bank's state is double-buffered: frame t reads buffer ``cur`` (the filtered state of t - 1, which the
smoothing step needs) and writes the other. The numbers equal the whole-array version's to rounding
(tests/test_marker_kalman.py compares it with the numpy reference in tests/marker_kalman_reference.py).
``cache=True`` keeps the machine code in ``__pycache__`` so only a process's first run compiles.
"""

from __future__ import annotations

import math

import numba
import numpy as np

X, V = 0, 1  # rows of the (buffer, row, filter, coordinate, marker) state
P00, P01, P11 = 0, 1, 2  # rows of the (buffer, row, filter, marker) covariances


@numba.njit(cache=True, nogil=True, error_model="numpy")
def step(XV: np.ndarray, P: np.ndarray, cur: int, lam: np.ndarray, p11_start: float, started: np.ndarray,
         sightings: np.ndarray, unseen: np.ndarray, count: np.ndarray, log_s: np.ndarray, energy: np.ndarray,
         slog: np.ndarray, z: np.ndarray, valid: np.ndarray, predict: bool, decay: float) -> None:
    """One frame of the bank in place: from buffer ``cur`` into the other, predicted (unless the first frame)
    and corrected with ``z`` (n x 3) where ``valid``; a marker's first sighting starts its filters there
    (velocity unknown); the discounted sums (``count`` n, ``log_s`` and ``energy`` K x n) take the innovations
    of markers seen at least twice before; ``slog`` (2 x K x n) keeps each filter's last s and its log (a seen
    marker's s settles, so the log is rarely taken). Per filter, each loop runs over the markers, contiguous in the
    state (its covariances, then each coordinate, then the sums), so that the compiler vectorises them (issue 39;
    each number as the marker-by-marker loop before it computed it)."""
    K, n = lam.shape[0], z.shape[0]
    new = 1 - cur
    first, upd, use = np.empty(n, np.bool_), np.empty(n, np.bool_), np.empty(n, np.bool_)
    zt = np.empty((3, n))
    for i in range(n):
        first[i] = valid[i] and not started[i]
        upd[i] = valid[i] and not first[i]
        use[i] = upd[i] and sightings[i] >= 2
        for c in range(3):
            zt[c, i] = z[i, c]
    S, K0, K1, EE = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    for k in range(K):
        q = lam[k]
        c00, c01, c11 = P[cur, P00, k], P[cur, P01, k], P[cur, P11, k]
        n00, n01, n11 = P[new, P00, k], P[new, P01, k], P[new, P11, k]
        for i in range(n):
            p00, p01, p11 = c00[i], c01[i], c11[i]
            if predict:
                a00 = p00 + 2 * p01 + p11 + q / 3
                a01 = p01 + p11 + q / 2
                p11 = p11 + q
                p00, p01 = a00, a01
            if first[i]:
                p00, p01, p11 = 1.0, 0.0, p11_start
            s = p00 + 1.0
            k0 = p00 / s if upd[i] else 0.0
            k1 = p01 / s if upd[i] else 0.0
            n00[i] = p00 - k0 * p00
            n01[i] = p01 - k0 * p01
            n11[i] = p11 - k1 * p01
            S[i], K0[i], K1[i], EE[i] = s, k0, k1, 0.0
        for c in range(3):
            xc, vc, xn, vn, zc = XV[cur, X, k, c], XV[cur, V, k, c], XV[new, X, k, c], XV[new, V, k, c], zt[c]
            for i in range(n):
                x, v = xc[i], vc[i]
                if predict:
                    x = x + v
                if first[i]:
                    x, v = zc[i], 0.0
                e = zc[i] - x if upd[i] else 0.0
                EE[i] += e * e
                xn[i] = x + K0[i] * e
                vn[i] = v + K1[i] * e
        ls_k, en_k, seen_s, seen_log = log_s[k], energy[k], slog[0, k], slog[1, k]
        for i in range(n):
            ls = ls_k[i] * decay
            en = en_k[i] * decay
            if use[i]:
                s = S[i]
                if s != seen_s[i]:  # a filter's s settles as its marker is seen on: its log kept
                    seen_s[i], seen_log[i] = s, math.log(s)
                ls += 3.0 * seen_log[i]
                en += EE[i] / s
            ls_k[i], en_k[i] = ls, en
    for i in range(n):
        count[i] = decay * count[i] + (3.0 if use[i] else 0.0)
        started[i] = started[i] or valid[i]
        sightings[i] += valid[i]
        unseen[i] = 0 if valid[i] else unseen[i] + 1


@numba.njit(cache=True, nogil=True)
def choose(log_s: np.ndarray, energy: np.ndarray, count: np.ndarray, inv_r: np.ndarray, log_r: np.ndarray,
           excluded: np.ndarray, ri: int, every_r: bool, pick: np.ndarray) -> int:
    """Each marker's filter (``pick``) and the shared r's index (returned): the least -2 log-likelihood
    ``log_s + energy / r`` (K x n) over the lambdas that r allows per marker; with ``every_r`` the r whose sum over
    the markers, ``c log r`` added, is least, else the r at ``ri`` kept. The markers innermost (the first least
    lambda per marker, as a loop over lambdas per marker finds it)."""
    K, n = log_s.shape
    best = np.empty(n)
    best_total, best_r = np.inf, ri
    for j in range(inv_r.shape[0] if every_r else 0):
        best[:] = np.inf
        for k in range(K):
            e_k, l_k, x = energy[k], log_s[k], excluded[j, k]
            for i in range(n):
                c = e_k[i] * inv_r[j] + l_k[i] + x
                if c < best[i]:
                    best[i] = c
        total = 0.0
        for i in range(n):
            total += best[i] + log_r[j] * count[i]
        if total < best_total:
            best_total, best_r = total, j
    best[:] = np.inf
    pick[:] = 0
    for k in range(K):
        e_k, l_k, x = energy[k], log_s[k], excluded[best_r, k]
        for i in range(n):
            c = e_k[i] * inv_r[best_r] + l_k[i] + x
            if c < best[i]:
                best[i], pick[i] = c, k
    return best_r


@numba.njit(cache=True, nogil=True)
def output(XV: np.ndarray, P: np.ndarray, cur: int, lam: np.ndarray, pick: np.ndarray, smooth: bool,
           out: np.ndarray) -> None:
    """Each marker's chosen filter (``pick``) in ``out`` (n x 3): its filtered state of this frame (buffer
    ``cur``), or with ``smooth`` the previous frame's smoothed by this one (one Rauch-Tung-Striebel step,
    F = [[1, 1], [0, 1]]; the prediction recomputed from the previous buffer as the step made it)."""
    old = 1 - cur
    for i in range(out.shape[0]):
        k = pick[i]
        if not smooth:
            for c in range(3):
                out[i, c] = XV[cur, X, k, c, i]
            continue
        q = lam[k]
        f00, f01, f11 = P[old, P00, k, i], P[old, P01, k, i], P[old, P11, k, i]
        a00 = f00 + 2 * f01 + f11 + q / 3
        a01 = f01 + f11 + q / 2
        a11 = f11 + q
        det = a00 * a11 - a01 * a01
        j00 = ((f00 + f01) * a11 - f01 * a01) / det
        j01 = (-(f00 + f01) * a01 + f01 * a00) / det
        for c in range(3):
            fx, fv = XV[old, X, k, c, i], XV[old, V, k, c, i]
            out[i, c] = fx + j00 * (XV[cur, X, k, c, i] - (fx + fv)) + j01 * (XV[cur, V, k, c, i] - fv)


@numba.njit(cache=True, nogil=True)
def frame(XV: np.ndarray, P: np.ndarray, cur: int, lam: np.ndarray, p11_start: float, started: np.ndarray,
          sightings: np.ndarray, unseen: np.ndarray, count: np.ndarray, log_s: np.ndarray, energy: np.ndarray,
          slog: np.ndarray, z: np.ndarray, valid: np.ndarray, predict: bool, decay: float, inv_r: np.ndarray,
          log_r: np.ndarray, excluded: np.ndarray, ri: int, every_r: bool, pick: np.ndarray, smooth: bool, max_gap: int,
          out: np.ndarray, ok: np.ndarray) -> int:
    """:func:`step`, :func:`choose` and :func:`output` as one call (``cur`` the buffer :func:`step` reads; the
    output reads the other), and each marker's validity in ``ok`` (started, unseen at most ``max_gap`` frames); the
    shared r's index returned. Why one call: each call from Python costs a dispatch of its ~10-15 arguments
    (issue 39: ~3 µs of a ~20 µs frame)."""
    step(XV, P, cur, lam, p11_start, started, sightings, unseen, count, log_s, energy, slog, z, valid, predict, decay)
    ri = choose(log_s, energy, count, inv_r, log_r, excluded, ri, every_r, pick)
    output(XV, P, 1 - cur, lam, pick, smooth, out)
    for i in range(ok.shape[0]):
        ok[i] = started[i] and unseen[i] <= max_gap
    return ri
