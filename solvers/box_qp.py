"""Warm-started active-set solver for box-constrained QPs with a fixed Hessian.

    minimise  1/2 x' H x + f' x   subject to  lower <= x <= upper,   H symmetric positive definite.

The per-frame blendshape fit (Curio et al. 2006 §2.3; Lewis et al. 2014 §5.2) is this problem
with H fixed per marker-visibility pattern and only f changing per frame; from one frame to the
next the set of weights strictly inside their limits (the free set F) rarely changes, and it is
small when the fit is sparse (most shapes rest at a bound). This solver works on F alone: it keeps
the inverse of H_FF, updated through the Schur complement when variables enter or leave F (O(k^2)
for k = |F|, no O(m^3)), so a frame whose free set is unchanged costs one k x k product, one k x m
product and the KKT check. A dual active-set solver such as DAQP works on the *active* bounds
instead, which at 1000 shapes with ~25 free means factorising ~975 constraints.

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
"""

from __future__ import annotations

import numpy as np

_MIN, _MAX = np.minimum.reduce, np.maximum.reduce  # the ufunc reductions, without ndarray.min's wrapper


class BoxQP:
    """Solver state for one Hessian: the free set of the last solve and the inverse of its block.

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
        self._fixed = self.lo == self.hi
        self._ref = np.where(np.isfinite(self.lo), self.lo, np.where(np.isfinite(self.hi), self.hi, 0.0))
        self._span = np.where(np.isfinite(self.hi), self.hi - self._ref, np.inf)  # y = x - ref in [ylo, span]
        self._ylo = np.where(np.isfinite(self.lo), self.lo - self._ref, -np.inf)
        self._Href = np.zeros(self.m) if not np.any(self._ref) else self.H @ self._ref
        uniform = len(np.unique(self._ylo)) == 1 and len(np.unique(self._span)) == 1
        self._box = (float(self._ylo[0]), float(self._span[0])) if uniform and self.m else None
        self._ref_zero = not np.any(self._ref)
        self.tol = 1e-11 * float(max(1.0, np.abs(np.diagonal(self.H)).max()))
        self.max_iter = 3 * self.m + 10 if max_iter is None else int(max_iter)
        self.iterations = 0
        self.warm(np.clip(np.zeros(self.m), self.lo, self.hi))

    # ------------------------------------------------------------------ state
    def warm(self, x: np.ndarray) -> None:
        """Start the next solve from the feasible point ``x``: free where strictly inside the box."""
        x = np.clip(np.asarray(x, dtype=np.float64), self.lo, self.hi)
        up = (x >= self.hi) & ~self._fixed
        self._free_set(np.flatnonzero((x > self.lo) & (x < self.hi)), up, (x - self._ref))

    def _free_set(self, F: np.ndarray, up: np.ndarray, y: np.ndarray) -> None:
        """Set F (order of the inverse), the variables at their upper bound, and derived constants."""
        self.F = np.asarray(F, dtype=np.intp)
        self._up = up
        self._invert()
        self._y = y[self.F].copy()  # current feasible point on F
        self._derive()

    def _invert(self) -> None:
        F = self.F
        self.Minv = np.linalg.inv(self.H[np.ix_(F, F)]) if len(F) else np.zeros((0, 0))
        self._fresh = True

    def _derive(self) -> None:
        """Constants of the current (F, upper) partition: the bounded variables' values, the gradient
        offset c = H ref + H y_bounded, the multiplier signs, y's limits on F."""
        F, up = self.F, self._up
        self.HF = self.H[F]
        self._nMinv = -self.Minv
        self._checked = False  # the inverse changed: check its residual at the next solution
        yb = np.where(up, self._span, 0.0)
        yb[F] = 0.0
        self._xb = np.where(up, self.hi, self._ref)  # the bounded variables' values (exact limits)
        U = np.flatnonzero(up)
        self._c = self._Href + yb[U] @ self.H[U] if len(U) else self._Href.copy()
        sgn = np.where(up, -1.0, 1.0)
        sgn[self._fixed] = 0.0
        sgn[F] = 0.0
        self._sgn = sgn
        self._ylo_F, self._yhi_F = self._ylo[F], self._span[F]
        self._refF = None if self._ref_zero else self._ref[F]

    def _add(self, J: np.ndarray) -> bool:
        """Variables J enter F: block Schur-complement update of the inverse, partition constants
        updated in place. False if H_FF loses rank."""
        F, H = self.F, self.H
        HJ = H[J]
        Bj = HJ[:, F]  # a x k
        U = self.Minv @ Bj.T  # k x a
        S = HJ[:, J] - Bj @ U
        if len(J) == 1:
            if not S[0, 0] > 0:
                return False
            Sinv = 1.0 / S
        else:
            try:
                Sinv = np.linalg.inv(S)
            except np.linalg.LinAlgError:
                return False
            if not (np.all(np.isfinite(Sinv)) and np.all(np.diagonal(Sinv) > 0)):
                return False
        k, a = len(F), len(J)
        US = U @ Sinv
        M = np.empty((k + a, k + a))
        np.matmul(US, U.T, out=M[:k, :k])
        M[:k, :k] += self.Minv
        M[:k, k:] = -US
        M[k:, :k] = M[:k, k:].T
        M[k:, k:] = Sinv
        self.Minv, self._nMinv = M, -M
        self._fresh = self._checked = False
        up = self._up[J]
        y_new = np.where(up, self._span[J], 0.0)
        if up.any():
            self._c -= y_new[up] @ HJ[up]
            self._up[J] = False
        self._sgn[J] = 0.0
        self.F = np.concatenate([F, J])
        self.HF = np.concatenate([self.HF, HJ])
        self._y = np.concatenate([self._y, y_new])
        self._limits()
        return True

    def _remove(self, P: np.ndarray, to_upper: np.ndarray) -> None:
        """Positions P of F leave it (to their upper bound where ``to_upper``): the inverse downdated."""
        keep = np.ones(len(self.F), bool)
        keep[P] = False
        M = self.Minv
        if len(P) == 1:
            e = M[keep, P[0]]
            Mk = M[keep][:, keep]
            Mk -= np.multiply.outer(e, e / M[P[0], P[0]])
        else:
            E = M[np.ix_(keep, P)]
            Mk = M[np.ix_(keep, keep)] - E @ np.linalg.solve(M[np.ix_(P, P)], E.T)
        self.Minv, self._nMinv = Mk, -Mk
        self._fresh = self._checked = False
        V = self.F[P]
        Vu, Vl = V[to_upper], V[~to_upper]
        if len(Vu):
            self._up[Vu] = True
            self._sgn[Vu] = -1.0
            self._xb[Vu] = self.hi[Vu]
            self._c += self._span[Vu] @ self.H[Vu]
        self._sgn[Vl] = 1.0
        self._xb[Vl] = self._ref[Vl]
        self.F = self.F[keep]
        self.HF = self.HF[keep]
        self._y = self._y[keep]
        self._limits()

    def _limits(self) -> None:
        """y's limits and the reference point on F (only where the box is not the same for all)."""
        if self._box is None:
            self._ylo_F, self._yhi_F = self._ylo[self.F], self._span[self.F]
        if not self._ref_zero:
            self._refF = self._ref[self.F]

    # ------------------------------------------------------------------ solve
    def solve(self, f: np.ndarray) -> np.ndarray | None:
        """The minimiser for linear term ``f`` (None if the iteration limit is reached or H_FF is singular).

        Block principal pivoting first (Judice & Pires 1994; Portugal, Judice & Vicente 1994 for
        bounds): every primal- and dual-infeasible variable changes side at once, usually converging
        in one or two passes from the last frame's partition. If the count of infeasibilities stops
        falling for ``_TRIES`` passes, the primal method (monotone, finite) finishes from the clipped point.
        """
        best, tries = self.m + 1, self._TRIES
        for it in range(1, self.max_iter + 1):
            y, g, fc = self._subproblem(f)
            if g is None:
                continue
            inside = not len(y) or self._inside(y)
            g *= self._sgn
            if inside and _MIN(g) >= -self.tol:
                return self._done(it, y)
            tol = self.tol + 1e-12 * float(np.abs(fc).max())  # rounding in g grows with |f|
            J = np.flatnonzero(g < -tol)
            below = above = None
            if not inside:
                lo_F, hi_F = self._bounds_F()
                below, above = y < lo_F, y > hi_F
            n_bad = len(J) + (0 if inside else int(np.count_nonzero(below | above)))
            if n_bad == 0:
                return self._done(it, y)
            if n_bad < best and len(J) <= max(self._BLOCK, len(y)):
                best, tries = n_bad, self._TRIES
            elif tries > 0 and len(J) <= max(self._BLOCK, len(y)):
                tries -= 1
            else:  # not converging, or far from the solution (a cold start): one variable at a time
                return self._primal(f, y, it)
            self._y = y
            if not inside:
                P = np.flatnonzero(below | above)
                self._remove(P, above[P])
            if len(J) and not self._add(J):
                return None
        self.iterations = self.max_iter
        return None

    _TRIES = 3  # passes without fewer infeasibilities before the primal method takes over
    _BLOCK = 8  # more entering variables than this (and than |F|): the primal method, one at a time

    def _subproblem(self, f: np.ndarray):
        """y on F with the bounded variables fixed, the gradient g = H x + f and fc = f + c; g None
        when the updated inverse drifted and was refactored (solve again)."""
        fc = f + self._c
        y = self._nMinv @ fc[self.F]
        g = y @ self.HF
        g += fc
        if not self._checked:  # after an update of the inverse: is H_FF y = -fc_F still solved?
            r, b = g[self.F], fc[self.F]
            if r @ r > 1e-20 * (b @ b) + self.tol * self.tol and not self._fresh:
                self._invert()  # drifted: refactor and solve again (a fresh inverse is as good as H allows)
                self._nMinv = -self.Minv
                return y, None, fc
            self._checked = True
        return y, g, fc

    def _done(self, it: int, y: np.ndarray) -> np.ndarray:
        self.iterations = it
        self._y = y
        x = self._xb.copy()
        x[self.F] = y if self._refF is None else self._refF + y
        return x

    def _primal(self, f: np.ndarray, y: np.ndarray, start: int) -> np.ndarray | None:
        """Primal active-set passes (Nocedal & Wright §16.5) from the current partition's clipped point."""
        x = self._xb.copy()
        x[self.F] = y if self._refF is None else self._refF + y
        self.warm(x)
        for it in range(start + 1, self.max_iter + 1):
            y, g, fc = self._subproblem(f)
            if g is None:
                continue
            if len(y) and not self._inside(y):
                lo_F, hi_F = self._bounds_F()
                self._block(y, y < lo_F, y > hi_F)
                continue
            self._y = y
            g *= self._sgn
            j = int(np.argmin(g))
            if g[j] < -(self.tol + 1e-12 * float(np.abs(fc).max())):  # the most violated bound enters F
                if not self._add(np.array([j])):
                    return None
                continue
            return self._done(it, y)
        self.iterations = self.max_iter
        return None

    def _bounds_F(self):
        return self._box if self._box is not None else (self._ylo_F, self._yhi_F)

    def _inside(self, y: np.ndarray) -> bool:
        box = self._box
        if box is not None:
            return _MIN(y) >= box[0] and _MAX(y) <= box[1]
        return bool(np.all(y >= self._ylo_F) and np.all(y <= self._yhi_F))

    def _block(self, y: np.ndarray, below: np.ndarray, above: np.ndarray) -> None:
        """Step from the feasible point towards ``y`` until the first limit; blocking variables leave F."""
        cur = self._y
        p = y - cur
        viol = below | above
        with np.errstate(divide="ignore", invalid="ignore"):
            lo_F, hi_F = self._bounds_F()
            t = np.where(below, lo_F - cur, hi_F - cur) / p
        t = np.where(viol, np.maximum(t, 0.0), np.inf)
        alpha = float(min(t.min(), 1.0))
        self._y = cur + alpha * p
        hit = np.flatnonzero(t <= alpha * (1 + 1e-12) + 1e-300)
        self._remove(hit, above[hit])
