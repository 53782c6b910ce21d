"""Compiled (numba) passes of the box QP (``solvers.box_qp.BoxQP``; the method is described there).

As numpy calls a pass cost ~20 calls of per-call overhead on k ~ 16 free weights; here one call runs every
pass of a solve (docs/performance.md, "Compiled kernels (numba)"). The state lives in a few arrays (rows named
below) that the kernels update in place; ``cache=True`` keeps the machine code in ``__pycache__``. Kept apart
from the class so that importing ``solvers.box_qp`` (every CLI command does, through the mode registry) does
not import numba: the class imports this module when a first solver is made. The inner loops are written for
the compiler to vectorise (sums reassociated, ``_FAST``; four factor rows, or four rows of H, per sweep) and
along rows (the factor is row-major): docs/performance.md, "The qp mode's box QP near the floor".
"""

from __future__ import annotations

import math

import numba
import numpy as np

# rows of the per-variable state V (m columns): limits, the reference point and y's limits (y = x - ref in
# [YLO, SPAN]), H ref, minus the gradient offset c (f + c = the gradient at y = 0 on F), the multiplier signs
# (0 on F and fixed variables), the bounded variables' values, at the upper limit (1.0), fixed (lo == hi),
# the gradient, minus f + c, the point on F (by position), the subproblem's solution (by position) and scratch
LO, HI, REF, SPAN, YLO, HREF, NC, SGN, XB, UP, FIXED, G, NFC, Y, S, W = range(16)
N_ROWS = 16
# rows of the integer state I: F (by position), then scratch: entering variables, leaving positions, to upper
FREE, ENTERING, LEAVING, ABOVE = range(4)
_TRIES = 3  # passes without fewer infeasibilities before the primal method takes over
_UPDATE = 15.0  # a rank-1 update element costs this many factor multiply-adds (strided; 7-30 measured alike)
_BLOCK = 8  # more entering variables than this (and than |F|): the primal method, one at a time
# helpers called only from the kernels: no CPython wrapper to compile
# (sums in any order, multiply-adds fused: the dot products vectorise; no assumption about NaN or inf)
_FAST = {"reassoc", "contract"}
_inner = numba.njit(cache=True, nogil=True, no_cpython_wrapper=True, no_cfunc_wrapper=True, fastmath=_FAST)


@_inner
def _factor(H, I, k, L, start):
    """Rows ``start`` .. k-1 of the Cholesky factor of H_FF in L's lower triangle (row-major; row i depends only
    on rows < i, so rows that F's change left in place are kept: a variable appended costs O(k^2)). Returns the
    number of leading rows now valid: k, or the row at which H_FF is not positive definite. Four rows at a time
    share each earlier row's loads (three times faster than one at a time at k ~ 80)."""
    F = I[FREE]
    i0 = start
    while i0 < k:
        R = min(4, k - i0)
        if R == 4:  # the block's columns before it, four dot products per earlier row
            Ha, Hb, Hc, Hd = H[F[i0]], H[F[i0 + 1]], H[F[i0 + 2]], H[F[i0 + 3]]
            La, Lb, Lc, Ld = L[i0], L[i0 + 1], L[i0 + 2], L[i0 + 3]
            for j in range(i0):
                Lj, fj = L[j], F[j]
                ta, tb, tc, td = Ha[fj], Hb[fj], Hc[fj], Hd[fj]
                for p in range(j):
                    lp = Lj[p]
                    ta -= La[p] * lp
                    tb -= Lb[p] * lp
                    tc -= Lc[p] * lp
                    td -= Ld[p] * lp
                d = Lj[j]
                La[j], Lb[j], Lc[j], Ld[j] = ta / d, tb / d, tc / d, td / d
        else:
            for i in range(i0, i0 + R):
                Hi, Li = H[F[i]], L[i]
                for j in range(i0):
                    Lj = L[j]
                    t = Hi[F[j]]
                    for p in range(j):
                        t -= Li[p] * Lj[p]
                    Li[j] = t / Lj[j]
        for i in range(i0, i0 + R):  # the block's own triangle, row by row
            Hi, Li = H[F[i]], L[i]
            for j in range(i0, i):
                Lj = L[j]
                t = Hi[F[j]]
                for p in range(j):
                    t -= Li[p] * Lj[p]
                Li[j] = t / Lj[j]
            s = Hi[F[i]]
            for p in range(i):
                s -= Li[p] * Li[p]
            if not s > 0.0:
                return i
            Li[i] = math.sqrt(s)
        i0 += R
    return k


@_inner
def _subproblem(H, V, I, k, L, f):
    """S[:k] = y on F with the bounded variables fixed (H_FF y = -fc_F), G = H x + f, NFC = -(f + c);
    returns max |f + c| (the gradient tolerance grows with it)."""
    m = H.shape[0]
    F, nfc, g, y = I[FREE], V[NFC], V[G], V[S]
    big = 0.0
    for j in range(m):
        v = V[NC, j] - f[j]
        nfc[j] = v
        big = max(big, abs(v))
    for i in range(k):  # forward: L z = -fc_F
        t = nfc[F[i]]
        for p in range(i):
            t -= L[i, p] * y[p]
        y[i] = t / L[i, i]
    for i in range(k - 1, -1, -1):  # back: L' y = z, by rows of L (contiguous)
        yi = y[i] / L[i, i]
        y[i] = yi
        Li = L[i]
        for p in range(i):
            y[p] -= yi * Li[p]
    for j in range(m):
        g[j] = -nfc[j]
    p = 0
    while p + 4 <= k:  # four rows of H per sweep of g: one load and store of g per four multiply-adds
        ya, yb, yc, yd = y[p], y[p + 1], y[p + 2], y[p + 3]
        Ha, Hb, Hc, Hd = H[F[p]], H[F[p + 1]], H[F[p + 2]], H[F[p + 3]]
        for j in range(m):
            g[j] += ya * Ha[j] + yb * Hb[j] + yc * Hc[j] + yd * Hd[j]
        p += 4
    for q in range(p, k):
        yq, row = y[q], H[F[q]]
        for j in range(m):
            g[j] += yq * row[j]
    return big


@_inner
def _inside(V, I, k):
    F, y = I[FREE], V[S]
    for p in range(k):
        v = F[p]
        if y[p] < V[YLO, v] or y[p] > V[SPAN, v]:
            return False
    return True


@_inner
def _keep(V, k):
    """The subproblem's solution becomes the current point."""
    for p in range(k):
        V[Y, p] = V[S, p]


@_inner
def _add(H, V, I, k, n):
    """Variables I[ENTERING, :n] enter F at their current limits (appended; refactored at the next pass)."""
    F, y, nc = I[FREE], V[Y], V[NC]
    m = H.shape[0]
    for q in range(n):
        j = I[ENTERING, q]
        F[k] = j
        if V[UP, j] != 0.0:
            span = V[SPAN, j]
            y[k] = span
            row = H[j]
            for c in range(m):
                nc[c] += span * row[c]
            V[UP, j] = 0.0
        else:
            y[k] = 0.0
        V[SGN, j] = 0.0
        k += 1
    return k


@_inner
def _delete(L, p, valid, w):
    """Row and column p (< valid) out of the factor's first ``valid`` rows: the rows below move up one and
    their trailing block takes the rank-1 update by the deleted column (Golub & Van Loan, Matrix
    Computations, 4th ed. 2013, §6.5.4), O((valid - p)^2) instead of refactoring rows p .. valid - 1."""
    for i in range(p + 1, valid):
        w[i] = L[i, p]
        for j in range(p):
            L[i - 1, j] = L[i, j]
        for j in range(p + 1, i + 1):
            L[i - 1, j - 1] = L[i, j]
    for j in range(p, valid - 1):
        a, b = L[j, j], w[j + 1]
        r = math.sqrt(a * a + b * b)
        c, s = a / r, b / r  # a Givens rotation: |c|, |s| <= 1, so nearly collinear rows lose nothing (review)
        L[j, j] = r
        for i in range(j + 1, valid - 1):
            li, wi = L[i, j], w[i + 1]
            L[i, j] = c * li + s * wi
            w[i + 1] = c * wi - s * li


@_inner
def _remove(H, V, I, k, n, L, valid):
    """Positions I[LEAVING, :n] (ascending) of F leave it, to the upper limit where I[ABOVE]; F keeps its order.
    The factor follows: rows from some leaving position p_t on are left to be refactored, and the deletions
    before it are rank-1 updates of the rows up to p_t (``_delete``), p_t chosen to minimise the estimated
    cost (an update element costs ~_UPDATE factor multiply-adds: strided, measured). Returns (|F|, rows of the
    factor valid)."""
    F, y, nc = I[FREE], V[Y], V[NC]
    m = H.shape[0]
    best, cut, t_best = np.inf, valid, 0
    s1, s2, t = 0.0, 0.0, 0
    while True:  # t deletions updated, the factor refactored from the next one's position (or none)
        at = I[LEAVING, t] if t < n and I[LEAVING, t] < valid else valid
        cost = _UPDATE * (t * at * at - 2.0 * at * s1 + s2) + (valid * valid * valid - at * at * at) / 6.0
        if cost < best:
            best, cut, t_best = cost, at, t
        if at == valid:
            break
        s1 += at
        s2 += at * at
        t += 1
    for q in range(t_best - 1, -1, -1):
        _delete(L, I[LEAVING, q], cut, V[W])
        cut -= 1
    valid = cut
    q, out = 0, 0
    for p in range(k):
        if q < n and I[LEAVING, q] == p:
            v = F[p]
            if I[ABOVE, q]:
                V[UP, v] = 1.0
                V[SGN, v] = -1.0
                V[XB, v] = V[HI, v]
                span, row = V[SPAN, v], H[v]
                for c in range(m):
                    nc[c] -= span * row[c]
            else:
                V[SGN, v] = 1.0
                V[XB, v] = V[REF, v]
            q += 1
        else:
            F[out], y[out] = F[p], y[p]
            out += 1
    return out, valid


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def warm(H: np.ndarray, V: np.ndarray, I: np.ndarray, x: np.ndarray) -> int:
    """Start from the feasible point clip(x): free where strictly inside the box; returns |F|."""
    m = H.shape[0]
    F, y, nc = I[FREE], V[Y], V[NC]
    k = 0
    for j in range(m):
        lo, hi = V[LO, j], V[HI, j]
        v = min(max(x[j], lo), hi)
        up = v >= hi and V[FIXED, j] == 0.0
        V[UP, j] = 1.0 if up else 0.0
        V[XB, j] = hi if up else V[REF, j]
        nc[j] = -V[HREF, j]
        if v > lo and v < hi:
            F[k] = j
            y[k] = v - V[REF, j]
            k += 1
            V[SGN, j] = 0.0
        else:
            V[SGN, j] = 0.0 if V[FIXED, j] != 0.0 else (-1.0 if up else 1.0)
    for u in range(m):
        if V[UP, u] != 0.0:
            span, row = V[SPAN, u], H[u]
            for c in range(m):
                nc[c] -= span * row[c]
    return k


@_inner
def _done(V, I, k, x):
    F, y = I[FREE], V[Y]
    for j in range(x.shape[0]):
        x[j] = V[XB, j]
    for p in range(k):
        x[F[p]] = V[REF, F[p]] + y[p]


@_inner
def _grown(L, k, valid):
    """L with room for a k x k factor (capacity doubles, never shrinks; the valid rows carried over)."""
    if k <= L.shape[0]:
        return L
    cap = max(k, 2 * L.shape[0])
    out = np.empty((cap, cap))
    for i in range(valid):  # loops, not a slice assignment: that alone took seconds to compile
        for j in range(i + 1):
            out[i, j] = L[i, j]
    return out


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def solve(H: np.ndarray, V: np.ndarray, I: np.ndarray, meta: np.ndarray, L: np.ndarray, f: np.ndarray,
          x: np.ndarray, tol: float, max_iter: int) -> tuple[bool, int, np.ndarray]:
    """The passes of one solve (see the module doc); x written on success. Returns (ok, passes, L), passes -1
    when H_FF is not positive definite; meta = [k, rows of the factor valid] is the state between calls."""
    k, valid = meta[0], meta[1]
    m = H.shape[0]
    best, tries = m + 1, _TRIES
    it = max_iter - max_iter + 1  # 1, typed int64: a literal would compile _primal a second time for it
    while it <= max_iter:
        if valid < k:
            L = _grown(L, k, valid)
            valid = _factor(H, I, k, L, valid)
            if valid < k:
                meta[0], meta[1] = k, valid
                return False, -1, L  # H_FF not positive definite: no pass counted (-1)
        big = _subproblem(H, V, I, k, L, f)
        inside = k == 0 or _inside(V, I, k)
        g, sgn = V[G], V[SGN]
        worst = np.inf
        for j in range(m):
            g[j] *= sgn[j]
            worst = min(worst, g[j])
        if inside and worst >= -tol:
            _keep(V, k)
            _done(V, I, k, x)
            meta[0], meta[1] = k, valid
            return True, it, L
        gtol = tol + 1e-12 * big
        nJ = 0
        for j in range(m):
            if g[j] < -gtol:
                I[ENTERING, nJ] = j
                nJ += 1
        nP = 0
        if not inside:
            F, y = I[FREE], V[S]
            for p in range(k):
                v = F[p]
                above = y[p] > V[SPAN, v]
                if y[p] < V[YLO, v] or above:
                    I[LEAVING, nP], I[ABOVE, nP] = p, 1 if above else 0
                    nP += 1
        n_bad = nJ + nP
        if n_bad == 0:
            _keep(V, k)
            _done(V, I, k, x)
            meta[0], meta[1] = k, valid
            return True, it, L
        if n_bad < best and nJ <= max(_BLOCK, k):
            best, tries = n_bad, _TRIES
        elif tries > 0 and nJ <= max(_BLOCK, k):
            tries -= 1
        else:  # not converging, or far from the solution (a cold start): one variable at a time
            return _primal(H, V, I, meta, L, f, x, tol, max_iter, k, it)
        _keep(V, k)
        if nP:
            k, valid = _remove(H, V, I, k, nP, L, valid)
        if nJ:
            k = _add(H, V, I, k, nJ)
        it += 1
    meta[0], meta[1] = k, valid
    return False, max_iter, L


@_inner
def _primal(H, V, I, meta, L, f, x, tol, max_iter, k, start):
    """Primal active-set passes (Nocedal & Wright §16.5) from the current partition's clipped point."""
    m = H.shape[0]
    _keep(V, k)
    _done(V, I, k, x)
    k = warm(H, V, I, x)
    valid = k - k  # 0, typed int64 (a literal 0 would compile _grown and _factor again for it)
    it = start + 1
    while it <= max_iter:
        if valid < k:
            L = _grown(L, k, valid)
            valid = _factor(H, I, k, L, valid)
            if valid < k:
                meta[0], meta[1] = k, valid
                return False, -1, L  # H_FF not positive definite: no pass counted (-1)
        big = _subproblem(H, V, I, k, L, f)
        if k and not _inside(V, I, k):  # step towards y until the first limit; blocking variables leave F
            F, y, cur = I[FREE], V[S], V[Y]
            alpha = 1.0
            for p in range(k):
                v = F[p]
                d = y[p] - cur[p]
                if y[p] < V[YLO, v]:
                    alpha = min(alpha, max((V[YLO, v] - cur[p]) / d, 0.0))
                elif y[p] > V[SPAN, v]:
                    alpha = min(alpha, max((V[SPAN, v] - cur[p]) / d, 0.0))
            reach = alpha * (1 + 1e-12) + 1e-300
            nP = 0
            for p in range(k):
                v = F[p]
                d = y[p] - cur[p]
                below, above = y[p] < V[YLO, v], y[p] > V[SPAN, v]
                if below or above:
                    t = max(((V[YLO, v] if below else V[SPAN, v]) - cur[p]) / d, 0.0)
                    if t <= reach:
                        I[LEAVING, nP], I[ABOVE, nP] = p, 1 if above else 0
                        nP += 1
                cur[p] += alpha * d
            if nP:
                k, valid = _remove(H, V, I, k, nP, L, valid)
            it += 1
            continue
        _keep(V, k)
        g, sgn = V[G], V[SGN]
        j_min, g_min = 0, np.inf
        for j in range(m):
            g[j] *= sgn[j]
            if g[j] < g_min:
                j_min, g_min = j, g[j]
        if g_min < -(tol + 1e-12 * big):  # the most violated bound enters F
            I[ENTERING, 0] = j_min
            k = _add(H, V, I, k, I[ENTERING, 0] * 0 + 1)  # one, typed int64 (not a literal: no second compile)
            it += 1
            continue
        _done(V, I, k, x)
        meta[0], meta[1] = k, valid
        return True, it, L
    meta[0], meta[1] = k, valid
    return False, max_iter, L


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def solve_frame(H: np.ndarray, V: np.ndarray, I: np.ndarray, meta: np.ndarray, L: np.ndarray, BtD: np.ndarray,
                s: np.ndarray, rows: np.ndarray, linear: np.ndarray, prior_f: np.ndarray, coef: float,
                prev: np.ndarray, restart: bool, f: np.ndarray, x: np.ndarray, tol: float,
                max_iter: int) -> tuple[bool, int, np.ndarray]:
    """A streamed frame of ``solvers.qp.FrameQP`` in one call: its linear term f = linear - B'M^2 s (the seen
    ``rows`` of s only) - prior_f - coef prev into ``f``, a warm start from ``prev`` when the pattern changed
    (``restart``), then :func:`solve`. As numpy calls around the solve this was ~15 calls of per-call overhead a
    frame (docs/performance.md, "`kalman` against `robust`")."""
    m, R = BtD.shape
    for j in range(m):
        row = BtD[j]
        acc = 0.0
        for r in range(R):
            if rows[r]:
                acc += row[r] * s[r]
        f[j] = ((linear[j] - acc) - prior_f[j]) - coef * prev[j]
    if restart:
        meta[0] = warm(H, V, I, prev)
        meta[1] = 0
    return solve(H, V, I, meta, L, f, x, tol, max_iter)


@numba.njit(cache=True, nogil=True)
def state(H: np.ndarray, limit_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """A new solver's state for H: V (the limit rows, H ref), I, meta, the factor's room and the tolerance, warm
    from 0. One call where it took ~12 numpy calls: kalman builds one per new visibility pattern (issue 39)."""
    m = H.shape[0]
    V = limit_rows.copy()
    for j in range(m):
        if V[REF, j] != 0.0:
            for i in range(m):
                acc = 0.0
                for c in range(m):
                    acc += H[i, c] * V[REF, c]
                V[HREF, i] = acc
            break
    I = np.zeros((4, m), np.int64)
    meta = np.zeros(2, np.int64)
    room = min(m, 32)
    big = 1.0
    for i in range(m):
        big = max(big, abs(H[i, i]))
    meta[0] = warm(H, V, I, np.zeros(m))
    return V, I, meta, np.empty((room, room)), 1e-11 * big
