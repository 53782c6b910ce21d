"""Warm-started active-set solver for box-constrained QPs with a fixed Hessian.

    minimise  1/2 x' H x + f' x   subject to  lower <= x <= upper,   H symmetric positive definite.

The per-frame blendshape fit (Curio et al. 2006 §2.3; Lewis et al. 2014 §5.2) is this problem
with H fixed per marker-visibility pattern and only f changing per frame; from one frame to the
next the set of weights strictly inside their limits (the free set F) rarely changes, and it is
small when the fit is sparse (most shapes rest at a bound). This solver works on F alone: it keeps
the Cholesky factor of H_FF, in F's order: a variable entering F appends a row (O(k^2) for k = |F|), one
leaving deletes its row and column by a rank-1 update of the rows after it (O((k - p)^2) at position p;
Golub & Van Loan, Matrix Computations, 4th ed. 2013, §6.5.4) or, where that is estimated dearer, the rows
from its position are refactored; no O(m^3), and no drift as an updated inverse has. A frame whose free
set is unchanged costs two k x k triangular solves, one k x m product and the KKT check. A dual active-set solver
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

The passes of a solve run in one compiled call (``solvers.box_qp_kernels``, numba; docs/performance.md,
"Compiled kernels (numba)").
"""

from __future__ import annotations

import numpy as np


class BoxQP:
    """Solver state for one Hessian: the free set of the last solve and the Cholesky factor of its block.

    ``solve(f)`` starts from the last solve's free set and point; ``warm(x)`` starts the next
    solve from any feasible point ``x`` instead (another workspace's solution, a reset).
    """

    @property
    def _k(self):  # noqa: ANN202 - the kernels' module, imported with the first solver (numba with it)
        from solvers import box_qp_kernels

        BoxQP._k = box_qp_kernels  # the class attribute now shadows this property: no import per solver
        return box_qp_kernels

    def __init__(self, H: np.ndarray, lower: np.ndarray, upper: np.ndarray, max_iter: int | None = None,
                 limit_rows: np.ndarray | None = None) -> None:
        """``limit_rows``: :meth:`limit_rows` of these limits, when many solvers share them (one per visibility
        pattern in solvers.qp), so that a new one only does what depends on H."""
        self.H = np.ascontiguousarray(H, dtype=np.float64)
        self.m = self.H.shape[0]
        if self.H.shape != (self.m, self.m):
            raise ValueError(f"H must be square, got {self.H.shape}")
        V = self.limit_rows(lower, upper, self.m) if limit_rows is None else limit_rows
        self._adopt(*self._k.state(self.H, V), max_iter)

    @classmethod
    def from_state(cls, H: np.ndarray, V: np.ndarray, I: np.ndarray, meta: np.ndarray, L: np.ndarray,
                   tol: float) -> BoxQP:
        """A solver on the state ``box_qp_kernels.state(H, limit rows)`` returned (made by a caller's compiled
        call, e.g. ``solvers.qp_kernels.pattern_workspace``), as ``BoxQP(H, lower, upper, limit_rows=...)``."""
        self = cls.__new__(cls)
        self.H, self.m = H, H.shape[0]
        self._adopt(V, I, meta, L, tol)
        return self

    def _adopt(self, V: np.ndarray, I: np.ndarray, meta: np.ndarray, L: np.ndarray, tol: float,
               max_iter: int | None = None) -> None:
        self._V, self._I, self._meta, self._L, self.tol = V, I, meta, L, tol
        self.lo, self.hi = V[self._k.LO], V[self._k.HI]
        self.max_iter = 3 * self.m + 10 if max_iter is None else int(max_iter)
        self.iterations = 0

    @staticmethod
    def limit_rows(lower: np.ndarray, upper: np.ndarray, m: int) -> np.ndarray:
        """The solver's per-variable state rows that depend on the limits alone (the kernels' V; H ref left 0)."""
        from solvers import box_qp_kernels as k

        lo = np.asarray(lower, dtype=np.float64).reshape(m)
        hi = np.asarray(upper, dtype=np.float64).reshape(m)
        V = np.zeros((k.N_ROWS, m))
        V[k.LO], V[k.HI], V[k.FIXED] = lo, hi, lo == hi
        ref = np.where(np.isfinite(lo), lo, np.where(np.isfinite(hi), hi, 0.0))
        V[k.REF] = ref
        V[k.SPAN] = np.where(np.isfinite(hi), hi - ref, np.inf)  # y = x - ref in [ylo, span]
        V[k.YLO] = np.where(np.isfinite(lo), lo - ref, -np.inf)
        return V

    @property
    def F(self) -> np.ndarray:
        """Indices of the free variables (strictly inside their limits at the last solution)."""
        return self._I[self._k.FREE, : self._meta[0]]

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
        self._meta[0] = self._k.warm(self.H, self._V, self._I, np.ascontiguousarray(x, dtype=np.float64))
        self._meta[1] = 0  # no row of the factor holds

    def solve(self, f: np.ndarray) -> np.ndarray | None:
        """The minimiser for linear term ``f`` (None if the iteration limit is reached or H_FF is singular).

        Block principal pivoting first (Judice & Pires 1994; Portugal, Judice & Vicente 1994 for
        bounds): every primal- and dual-infeasible variable changes side at once, usually converging
        in one or two passes from the last frame's partition. If the count of infeasibilities stops
        falling for three passes, the primal method (monotone, finite) finishes from the clipped point.
        """
        x = np.empty(self.m)
        ok, passes, self._L = self._k.solve(self.H, self._V, self._I, self._meta, self._L,
                                            np.ascontiguousarray(f, dtype=np.float64), x, self.tol, self.max_iter)
        if passes >= 0:
            self.iterations = passes
        return x if ok else None

    def solve_frame(self, BtD: np.ndarray, s: np.ndarray, rows: np.ndarray, linear: np.ndarray,
                    prior_f: np.ndarray, coef: float, prev: np.ndarray, restart: bool,
                    f: np.ndarray) -> np.ndarray | None:
        """:meth:`solve` for f = linear - BtD[:, rows] s[rows] - prior_f - coef prev (written into ``f``), after
        :meth:`warm` (``prev``) when ``restart``: a streamed frame of solvers.qp.FrameQP in one compiled call."""
        x = np.empty(self.m)
        ok, passes, self._L = self._k.solve_frame(self.H, self._V, self._I, self._meta, self._L, BtD, s, rows, linear,
                                                  prior_f, coef, prev, restart, f, x, self.tol, self.max_iter)
        if passes >= 0:
            self.iterations = passes
        return x if ok else None
