"""Warm-started active-set solver for box-constrained QPs with a fixed Hessian.

    minimise  1/2 x' H x + f' x   subject to  lower <= x <= upper,   H symmetric positive definite.

The per-frame blendshape fit (Curio et al. 2006 §2.3; Lewis et al. 2014 §5.2) is this problem
with H fixed per marker-visibility pattern and only f changing per frame; from one frame to the
next the set of weights strictly inside their limits (the free set F) rarely changes, and it is
small when the fit is sparse (most shapes rest at a bound). This solver works on F alone: it keeps
the Cholesky factor of H_FF (recomputed when variables enter or leave F: O(k^3 / 3) for k = |F|,
no O(m^3), and never drifts as an updated inverse does), so a frame whose free set is unchanged
costs two k x k triangular solves, one k x m product and the KKT check. A dual active-set solver
such as DAQP works on the *active* bounds instead, which at 1000 shapes with ~25 free means
factorising ~975 constraints.

Each pass solves the subproblem on F with the bounded variables fixed. Block principal pivoting
(Judice & Pires 1994; for bounds, the BLCP form) moves every primal-infeasible free variable to the
limit it crossed and every bounded variable whose multiplier has the wrong sign into F at once,
usually converging in one or two passes from the last frame's partition. When the number of
infeasibilities stops falling, or many variables want to enter at once (a cold start), the primal
active-set method takes over from the clipped point (Nocedal & Wright, Numerical Optimization, 2nd
ed. 2006, §16.5; for boxes the bounded-variable least squares of Stark & Parker 1995): a step from
the feasible point towards the subproblem solution until the first limit blocks, or the most
violated bound entering F. Its objective decreases strictly between subproblem minimisers, so it
terminates. The solution satisfies the KKT conditions to ``tol`` (scaled by H), the optimum DAQP
returns (tests/test_box_qp.py).

The passes run in one compiled (numba) call per solve: as numpy calls a pass cost ~20 calls of
per-call overhead on k ~ 16 free weights (docs/performance.md, "Compiled kernels (numba)"). The
state lives in a few arrays (rows named below) that the kernels update in place; ``cache=True``
keeps the machine code in ``__pycache__``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# rows of the per-variable state V (m columns): limits, the reference point and y's limits (y = x - ref in
# [YLO, SPAN]), H ref, minus the gradient offset c (f + c = the gradient at y = 0 on F), the multiplier signs
# (0 on F and fixed variables), the bounded variables' values, at the upper limit (1.0), fixed (lo == hi),
# the gradient, minus f + c, the point on F (by position) and the subproblem's solution (by position)
LO, HI, REF, SPAN, YLO, HREF, NC, SGN, XB, UP, FIXED, G, NFC, Y, S = range(15)
_N_ROWS = 15
# rows of the integer state I: F (by position), then scratch for entering variables and leaving positions
_F, _J, _P, _ABOVE = range(4)
_TRIES = 3  # passes without fewer infeasibilities before the primal method takes over
_BLOCK = 8  # more entering variables than this (and than |F|): the primal method, one at a time


@numba.njit(cache=True, nogil=True)
def _factor(H, I, k, L):
    """Cholesky factor of H_FF in L's lower triangle (row-major); False if H_FF is not positive definite."""
    F = I[_F]
    for j in range(k):
        fj = F[j]
        s = H[fj, fj]
        for p in range(j):
            s -= L[j, p] * L[j, p]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, k):
            t = H[F[i], fj]
            for p in range(j):
                t -= L[i, p] * L[j, p]
            L[i, j] = t / d
    return True


@numba.njit(cache=True, nogil=True)
def _subproblem(H, V, I, k, L, f):
    """S[:k] = y on F with the bounded variables fixed (H_FF y = -fc_F), G = H x + f, NFC = -(f + c);
    returns max |f + c| (the gradient tolerance grows with it)."""
    m = H.shape[0]
    F, nfc, g, y = I[_F], V[NFC], V[G], V[S]
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
    for i in range(k - 1, -1, -1):  # back: L' y = z
        t = y[i]
        for p in range(i + 1, k):
            t -= L[p, i] * y[p]
        y[i] = t / L[i, i]
    g[:] = 0.0
    for p in range(k):
        yp, row = y[p], H[F[p]]
        for j in range(m):
            g[j] += yp * row[j]
    for j in range(m):
        g[j] -= nfc[j]
    return big


@numba.njit(cache=True, nogil=True)
def _inside(V, I, k):
    F, y = I[_F], V[S]
    for p in range(k):
        v = F[p]
        if y[p] < V[YLO, v] or y[p] > V[SPAN, v]:
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _keep(V, k):
    """The subproblem's solution becomes the current point."""
    V[Y, :k] = V[S, :k]


@numba.njit(cache=True, nogil=True)
def _add(H, V, I, k, n):
    """Variables I[_J, :n] enter F at their current limits (appended; refactored at the next pass)."""
    F, y, nc = I[_F], V[Y], V[NC]
    m = H.shape[0]
    for q in range(n):
        j = I[_J, q]
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


@numba.njit(cache=True, nogil=True)
def _remove(H, V, I, k, n):
    """Positions I[_P, :n] (ascending) of F leave it, to the upper limit where I[_ABOVE]; the last position
    takes each one's place (F's order is free: the factor is recomputed at the next pass)."""
    F, y, nc = I[_F], V[Y], V[NC]
    m = H.shape[0]
    for q in range(n - 1, -1, -1):
        p = I[_P, q]
        v = F[p]
        if I[_ABOVE, q]:
            V[UP, v] = 1.0
            V[SGN, v] = -1.0
            V[XB, v] = V[HI, v]
            span, row = V[SPAN, v], H[v]
            for c in range(m):
                nc[c] -= span * row[c]
        else:
            V[SGN, v] = 1.0
            V[XB, v] = V[REF, v]
        k -= 1
        if p != k:
            F[p], y[p] = F[k], y[k]
    return k


@numba.njit(cache=True, nogil=True)
def _warm(H, V, I, x):
    """Start from the feasible point clip(x): free where strictly inside the box; returns |F|."""
    m = H.shape[0]
    F, y, nc = I[_F], V[Y], V[NC]
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


@numba.njit(cache=True, nogil=True)
def _done(V, I, k, x):
    F, y = I[_F], V[Y]
    x[:] = V[XB]
    for p in range(k):
        x[F[p]] = V[REF, F[p]] + y[p]


@numba.njit(cache=True, nogil=True)
def _grown(L, k):
    """L with room for a k x k factor (capacity doubles, never shrinks)."""
    if k <= L.shape[0]:
        return L
    return np.empty((max(k, 2 * L.shape[0]), max(k, 2 * L.shape[0])))


@numba.njit(cache=True, nogil=True)
def _solve(H, V, I, meta, L, f, x, tol, max_iter):
    """The passes of one solve (see the module doc); x written on success. Returns (ok, passes, L), passes -1
    when H_FF is not positive definite; meta = [k, dirty] is the state between calls."""
    k, dirty = meta[0], meta[1]
    m = H.shape[0]
    best, tries = m + 1, _TRIES
    it = 1
    while it <= max_iter:
        if dirty:
            L = _grown(L, k)
            if not _factor(H, I, k, L):
                meta[0], meta[1] = k, 1
                return False, -1, L  # H_FF not positive definite: no pass counted (-1)
            dirty = 0
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
            meta[0], meta[1] = k, 0
            return True, it, L
        gtol = tol + 1e-12 * big
        nJ = 0
        for j in range(m):
            if g[j] < -gtol:
                I[_J, nJ] = j
                nJ += 1
        nP = 0
        if not inside:
            F, y = I[_F], V[S]
            for p in range(k):
                v = F[p]
                above = y[p] > V[SPAN, v]
                if y[p] < V[YLO, v] or above:
                    I[_P, nP], I[_ABOVE, nP] = p, 1 if above else 0
                    nP += 1
        n_bad = nJ + nP
        if n_bad == 0:
            _keep(V, k)
            _done(V, I, k, x)
            meta[0], meta[1] = k, 0
            return True, it, L
        if n_bad < best and nJ <= max(_BLOCK, k):
            best, tries = n_bad, _TRIES
        elif tries > 0 and nJ <= max(_BLOCK, k):
            tries -= 1
        else:  # not converging, or far from the solution (a cold start): one variable at a time
            return _primal(H, V, I, meta, L, f, x, tol, max_iter, k, it)
        _keep(V, k)
        if nP:
            k = _remove(H, V, I, k, nP)
        if nJ:
            k = _add(H, V, I, k, nJ)
        dirty = 1
        it += 1
    meta[0], meta[1] = k, dirty
    return False, max_iter, L


@numba.njit(cache=True, nogil=True)
def _primal(H, V, I, meta, L, f, x, tol, max_iter, k, start):
    """Primal active-set passes (Nocedal & Wright §16.5) from the current partition's clipped point."""
    m = H.shape[0]
    _keep(V, k)
    _done(V, I, k, x)
    k = _warm(H, V, I, x)
    dirty = 1
    it = start + 1
    while it <= max_iter:
        if dirty:
            L = _grown(L, k)
            if not _factor(H, I, k, L):
                meta[0], meta[1] = k, 1
                return False, -1, L  # H_FF not positive definite: no pass counted (-1)
            dirty = 0
        big = _subproblem(H, V, I, k, L, f)
        if k and not _inside(V, I, k):  # step towards y until the first limit; blocking variables leave F
            F, y, cur = I[_F], V[S], V[Y]
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
                        I[_P, nP], I[_ABOVE, nP] = p, 1 if above else 0
                        nP += 1
                cur[p] += alpha * d
            k = _remove(H, V, I, k, nP)
            dirty = 1
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
            I[_J, 0] = j_min
            k = _add(H, V, I, k, 1)
            dirty = 1
            it += 1
            continue
        _done(V, I, k, x)
        meta[0], meta[1] = k, 0
        return True, it, L
    meta[0], meta[1] = k, dirty
    return False, max_iter, L


class BoxQP:
    """Solver state for one Hessian: the free set of the last solve and the Cholesky factor of its block.

    ``solve(f)`` starts from the last solve's free set and point; ``warm(x)`` starts the next
    solve from any feasible point ``x`` instead (another workspace's solution, a reset).
    """

    def __init__(self, H: np.ndarray, lower: np.ndarray, upper: np.ndarray, max_iter: int | None = None) -> None:
        self.H = np.ascontiguousarray(H, dtype=np.float64)
        self.m = self.H.shape[0]
        if self.H.shape != (self.m, self.m):
            raise ValueError(f"H must be square, got {self.H.shape}")
        self.lo = np.asarray(lower, dtype=np.float64).reshape(self.m)
        self.hi = np.asarray(upper, dtype=np.float64).reshape(self.m)
        V = np.zeros((_N_ROWS, self.m))
        V[LO], V[HI], V[FIXED] = self.lo, self.hi, self.lo == self.hi
        ref = np.where(np.isfinite(self.lo), self.lo, np.where(np.isfinite(self.hi), self.hi, 0.0))
        V[REF] = ref
        V[SPAN] = np.where(np.isfinite(self.hi), self.hi - ref, np.inf)  # y = x - ref in [ylo, span]
        V[YLO] = np.where(np.isfinite(self.lo), self.lo - ref, -np.inf)
        V[HREF] = self.H @ ref if np.any(ref) else 0.0
        self._V, self._I, self._meta = V, np.zeros((4, self.m), np.int64), np.zeros(2, np.int64)
        self._L = np.empty((min(self.m, 32), min(self.m, 32)))
        self.tol = 1e-11 * float(max(1.0, np.abs(np.diagonal(self.H)).max()))
        self.max_iter = 3 * self.m + 10 if max_iter is None else int(max_iter)
        self.iterations = 0
        self.warm(np.zeros(self.m))

    @property
    def F(self) -> np.ndarray:
        """Indices of the free variables (strictly inside their limits at the last solution)."""
        return self._I[_F, : self._meta[0]]

    @property
    def HF(self) -> np.ndarray:
        """The rows of H of the free variables (k x m)."""
        return self.H[self.F]

    @property
    def Minv(self) -> np.ndarray:
        """The inverse of H_FF (not used by the solve; for inspection)."""
        k = int(self._meta[0])
        return np.linalg.inv(self.H[np.ix_(self.F, self.F)]) if k else np.zeros((0, 0))

    def warm(self, x: np.ndarray) -> None:
        """Start the next solve from the feasible point ``x``: free where strictly inside the box."""
        self._meta[0] = _warm(self.H, self._V, self._I, np.ascontiguousarray(x, dtype=np.float64))
        self._meta[1] = 1

    def solve(self, f: np.ndarray) -> np.ndarray | None:
        """The minimiser for linear term ``f`` (None if the iteration limit is reached or H_FF is singular).

        Block principal pivoting first (Judice & Pires 1994; Portugal, Judice & Vicente 1994 for
        bounds): every primal- and dual-infeasible variable changes side at once, usually converging
        in one or two passes from the last frame's partition. If the count of infeasibilities stops
        falling for three passes, the primal method (monotone, finite) finishes from the clipped point.
        """
        x = np.empty(self.m)
        ok, passes, self._L = _solve(self.H, self._V, self._I, self._meta, self._L,
                                     np.ascontiguousarray(f, dtype=np.float64), x, self.tol, self.max_iter)
        if passes >= 0:
            self.iterations = passes
        return x if ok else None
