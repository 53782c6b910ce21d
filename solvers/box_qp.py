"""Warm-started active-set solver for box-constrained QPs with a fixed Hessian.

    minimise  1/2 x' H x + f' x   subject to  lower <= x <= upper,   H symmetric positive definite.

The per-frame blendshape fit (Curio et al. 2006 §2.3; Lewis et al. 2014 §5.2) is this problem
with H fixed per marker-visibility pattern and only f changing per frame; from one frame to the
next the set of weights strictly inside their limits (the free set F) rarely changes, and it is
small when the fit is sparse (most shapes rest at a bound). This solver works on F alone: it keeps
the Cholesky factor of H_FF (LAPACK ``dpotrf``, recomputed in place when variables enter or leave
F: O(k^3 / 3) for k = |F|, no O(m^3), and never drifts as an updated inverse does), so a frame whose
free set is unchanged costs two k x k triangular solves (``dpotrs``), one k x m product and the KKT
check, in buffers that only grow (no allocation in the steady state but the returned point). A dual
active-set solver such as DAQP works on the *active* bounds instead, which at 1000 shapes with ~25
free means factorising ~975 constraints.

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
from scipy.linalg.lapack import dpotrf, dpotrs

_MIN, _MAX = np.minimum.reduce, np.maximum.reduce  # the ufunc reductions, without ndarray.min's wrapper


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
        self._fc, self._g = np.empty(self.m), np.empty(self.m)
        self._k, self._cap = 0, 0
        self._grow(min(self.m, 32))
        self.warm(np.clip(np.zeros(self.m), self.lo, self.hi))

    # ------------------------------------------------------------------ state
    @property
    def F(self) -> np.ndarray:
        """Indices of the free variables (strictly inside their limits at the last solution)."""
        return self._F

    @property
    def HF(self) -> np.ndarray:
        """The rows of H of the free variables (k x m)."""
        return self._HF

    @property
    def Minv(self) -> np.ndarray:
        """The inverse of H_FF, from its factor (not used by the solve; for inspection)."""
        if not self._k or (self._dirty and not self._factor()):
            return np.zeros((0, 0)) if not self._k else np.full((self._k, self._k), np.nan)
        return dpotrs(self._L, np.eye(self._k), lower=1)[0]

    def warm(self, x: np.ndarray) -> None:
        """Start the next solve from the feasible point ``x``: free where strictly inside the box."""
        x = np.clip(np.asarray(x, dtype=np.float64), self.lo, self.hi)
        up = (x >= self.hi) & ~self._fixed
        F = np.flatnonzero((x > self.lo) & (x < self.hi))
        self._set_free(F)
        np.take(x - self._ref, F, out=self._y)
        self._up = up
        self._derive()

    def _grow(self, k: int) -> None:
        """Buffers for at least k free variables (capacity doubles, never shrinks)."""
        if k <= self._cap:
            return
        cap = min(self.m, max(k, 2 * self._cap))
        old = self._k
        Fb, yb, HFb = np.empty(cap, np.intp), np.empty(cap), np.empty((cap, self.m))
        if old:
            Fb[:old], yb[:old], HFb[:old] = self._F, self._y, self._HF
        self._Fb, self._yb, self._sb, self._HFb = Fb, yb, np.empty(cap), HFb
        self._Lb = np.empty(cap * cap)
        self._cap = cap
        self._views()

    def _views(self) -> None:
        k = self._k
        self._F, self._y, self._s, self._HF = self._Fb[:k], self._yb[:k], self._sb[:k], self._HFb[:k]

    def _set_free(self, F: np.ndarray) -> None:
        """F replaced (rows of H gathered); y on F left to the caller."""
        self._grow(len(F))
        self._k = len(F)
        self._views()
        self._F[:] = F
        self.H.take(self._F, axis=0, out=self._HF)
        self._dirty = True

    def _factor(self) -> bool:
        """Cholesky factor of H_FF in place (LAPACK dpotrf); False if H_FF is not positive definite."""
        self._dirty = False
        k = self._k
        if not k:
            self._L = None
            return True
        A = self._Lb[: k * k].reshape(k, k)
        self._HF.take(self._F, axis=1, out=A)
        self._L, info = dpotrf(A.T, lower=1, clean=0, overwrite_a=1)  # H_FF symmetric: A.T is A, Fortran order
        if info:
            self._dirty = True
        return info == 0

    def _derive(self) -> None:
        """Constants of the current (F, upper) partition: the bounded variables' values, the gradient
        offset c = H ref + H y_bounded, the multiplier signs, y's limits on F."""
        F, up = self._F, self._up
        yb = np.where(up, self._span, 0.0)
        yb[F] = 0.0
        self._xb = np.where(up, self.hi, self._ref)  # the bounded variables' values (exact limits)
        U = np.flatnonzero(up)
        self._nc = -(self._Href + yb[U] @ self.H[U] if len(U) else self._Href)  # minus c: f + c negated in one call
        sgn = np.where(up, -1.0, 1.0)
        sgn[self._fixed] = 0.0
        sgn[F] = 0.0
        self._sgn = sgn
        self._limits()

    def _add(self, J: np.ndarray) -> None:
        """Variables J enter F at their current limits (rows of H appended; refactored at the next pass)."""
        k = self._k
        self._grow(k + len(J))
        F, y, HF, H, up, span = self._Fb, self._yb, self._HFb, self.H, self._up, self._span
        for j in J.tolist():
            F[k] = j
            HF[k] = H[j]
            if up[j]:
                y[k] = span[j]
                self._nc += span[j] * HF[k]
                up[j] = False
            else:
                y[k] = 0.0
            self._sgn[j] = 0.0
            k += 1
        self._k = k
        self._changed()

    def _remove(self, P: np.ndarray, to_upper: np.ndarray) -> None:
        """Positions P (ascending) of F leave it (to their upper bound where ``to_upper``); the last position takes
        each one's place (F's order is free: the factor is recomputed at the next pass)."""
        k = self._k
        F, y, HF = self._Fb, self._yb, self._HFb
        for p, u in zip(reversed(P.tolist()), reversed(to_upper.tolist()), strict=True):  # P ascending
            v = int(F[p])
            if u:
                self._up[v] = True
                self._sgn[v] = -1.0
                self._xb[v] = self.hi[v]
                self._nc -= self._span[v] * HF[p]
            else:
                self._sgn[v] = 1.0
                self._xb[v] = self._ref[v]
            k -= 1
            if p != k:
                F[p], y[p] = F[k], y[k]
                HF[p] = HF[k]
        self._k = k
        self._changed()

    def _changed(self) -> None:
        self._views()
        self._limits()
        self._dirty = True

    def _limits(self) -> None:
        """y's limits and the reference point on F (only where the box is not the same for all)."""
        if self._box is None:
            self._ylo_F, self._yhi_F = self._ylo[self._F], self._span[self._F]
        self._refF = None if self._ref_zero else self._ref[self._F]

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
            if self._dirty and not self._factor():
                return None
            y, g, fc = self._subproblem(f)
            inside = not self._k or self._inside(y)
            g *= self._sgn
            if inside and _MIN(g) >= -self.tol:
                return self._done(it, y)
            tol = self._gtol(fc)
            J = (g < -tol).nonzero()[0]
            n_bad = len(J)
            if not inside:
                lo_F, hi_F = self._bounds_F()
                above = y > hi_F
                P = ((y < lo_F) | above).nonzero()[0]
                n_bad += len(P)
            if n_bad == 0:
                return self._done(it, y)
            if n_bad < best and len(J) <= max(self._BLOCK, self._k):
                best, tries = n_bad, self._TRIES
            elif tries > 0 and len(J) <= max(self._BLOCK, self._k):
                tries -= 1
            else:  # not converging, or far from the solution (a cold start): one variable at a time
                return self._primal(f, y, it)
            self._keep(y)
            if not inside:
                self._remove(P, above[P])
            if len(J):
                self._add(J)
        self.iterations = self.max_iter
        return None

    _TRIES = 3  # passes without fewer infeasibilities before the primal method takes over
    _BLOCK = 8  # more entering variables than this (and than |F|): the primal method, one at a time

    def _subproblem(self, f: np.ndarray):
        """y on F with the bounded variables fixed (H_FF y = -fc_F), the gradient g = H x + f and
        -fc = -(f + c), in the solver's buffers (valid until the next pass)."""
        nfc = np.subtract(self._nc, f, out=self._fc)
        y, g = self._s, self._g
        nfc.take(self._F, out=y)
        if self._k:
            dpotrs(self._L, y, lower=1, overwrite_b=1)
        np.dot(y, self._HF, out=g)
        g -= nfc
        return y, g, nfc

    def _gtol(self, fc: np.ndarray) -> float:
        """The tolerance on the gradient's sign: rounding in g grows with |f + c| (no |fc| temporary)."""
        return self.tol + 1e-12 * max(_MAX(fc), -_MIN(fc))

    def _keep(self, y: np.ndarray) -> None:
        """``y`` (the subproblem's buffer) becomes the current point: the two buffers swap."""
        if y is self._s:
            self._yb, self._sb = self._sb, self._yb
            self._y, self._s = self._s, self._y

    def _done(self, it: int, y: np.ndarray) -> np.ndarray:
        self.iterations = it
        self._keep(y)
        x = self._xb.copy()
        x[self._F] = y if self._refF is None else self._refF + y
        return x

    def _primal(self, f: np.ndarray, y: np.ndarray, start: int) -> np.ndarray | None:
        """Primal active-set passes (Nocedal & Wright §16.5) from the current partition's clipped point."""
        x = self._xb.copy()
        x[self._F] = y if self._refF is None else self._refF + y
        self.warm(x)
        for it in range(start + 1, self.max_iter + 1):
            if self._dirty and not self._factor():
                return None
            y, g, fc = self._subproblem(f)
            if self._k and not self._inside(y):
                lo_F, hi_F = self._bounds_F()
                self._block(y, y < lo_F, y > hi_F)
                continue
            self._keep(y)
            g *= self._sgn
            j = int(np.argmin(g))
            if g[j] < -self._gtol(fc):  # the most violated bound enters F
                self._add(np.array([j]))
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
        cur += alpha * p
        hit = np.flatnonzero(t <= alpha * (1 + 1e-12) + 1e-300)
        self._remove(hit, above[hit])
