"""A box QP with many more weights than marker coordinates, its linear algebra done in marker space.

    minimise  1/2 x' (D + J'J) x + f' x   subject to  lower <= x <= upper,

J the r seen (marker-weighted) rows of the basis (r = 3 x seen markers), D diagonal: a ridge or diagonal prior, the
temporal term and the floor of solvers.qp. Columns with D = 0 (solvers.pose_refine's six rigid columns: unbounded,
outside the prior) are eliminated first: for given x_G their least-squares fit leaves the same kind of box QP on
G with J_G projected off their range and f_G corrected, and x_P follows from x_G.

At 72 markers x 1000 shapes (r = 216, ~520 weights free) a weight-space method factors the free block H_FF (O(k^3))
and DAQP moves the active set one bound an iteration (~117 a frame, docs/performance.md, "`kalman` against
`robust`"). Here each pass is the primal-dual active-set method (Hintermueller, Ito & Kunisch 2003, SIAM J. Optim.
13(3), §2; for bounds it is block principal pivoting: every free weight outside its limits and every bounded one
whose multiplier has the wrong sign change sides at once; where the count of wrong sides stops falling for
PIVOT_BUDGET passes, the primal active-set method takes over from the clipped point, as solvers.box_qp does in
weight space: it terminates for any positive definite H) with the free block solved by Woodbury in marker space:
with S = I + J_F D_F^-1 J_F' (r x r however many weights are free), the fitted markers y = J x of the subproblem are

    y = S^-1 (J_A x_A - J_F D_F^-1 f_F),    x_F = -D_F^-1 (f_F + J_F' y),

and the multipliers of the bounded weights are the gradient D x + J'y + f there: two r x n products and one r x r
solve a pass. It ends exactly: when a pass leaves the partition as it was, x satisfies the KKT conditions
(tests/test_marker_space_qp.py). Where ``max_iter`` passes are not enough ``solve`` returns None and solvers.qp
falls back to DAQP.

S is kept between solves with its free set: a pass on an unchanged free set reuses its factor (a frame whose
partition did not move costs no factorisation); where at most ``WOODBURY`` columns changed sides, S^-1 b goes
through the kept factor and a k x k capacitance (Woodbury); otherwise S is updated by the columns that changed
(a symmetric rank-k product on its lower triangle) or, where fewer, formed from all columns' S less the bounded
ones', and refactored (O(r^3 / 3)); formed afresh every ``REFRESH`` updates against drift. Warm from the last
frame, the 72 x 1000 synthetic take's fit moves ~60-90 weights in the first pass and takes 3-5 passes. ``begin``
runs a solve's first passes ahead (kalman's held-out trial, split over two frames; docs/performance.md).

A solve call given ``frame_passes`` runs at most that many passes (0, the default: to the optimum; FRESH_PASSES from
a start that is not this QP's own last stop). Where they did not settle it returns the clipped point and keeps the
partition its last pass chose, and the next solve that starts from that very point goes on from it (on the same f,
with its count of wrong sides, so that a cycle still goes to the primal method). Streamed, a frame's QP barely moves
from the last, so each frame is one semismooth Newton step (block pivoting is one: Hintermueller, Ito & Kunisch 2003)
on the current data from the last iterate -- the real-time iteration of Diehl, Bock & Schloeder 2005 (SIAM J. Control
Optim. 43(5)): inexact on a frame, it tracks the optimum over frames, and on a QP that stays the same it reaches the
exact optimum (tests/test_marker_space_qp.py). kalman's stream asks for one pass (at 72 x 1000 its step a quarter
cheaper, the weights' RMSE against the synthetic takes' truth no worse: docs/performance.md, "`kalman` at 72 x 1000:
one block-pivoting pass a frame"); the qp mode and every offline solve stay exact.

A solve that starts where a peer stopped -- the same basis on a superset of its rows, D a scalar multiple of its own
(kalman's held-out trial warm from the frame's fit: a fold's markers out, another prior strength; the fit at a new
strength warm from the last frame's) -- may take its first S from the peer's kept one instead of its own, which was
factored for a free set frames ago: the peer's block of our rows, scaled, the pose's range projected off (a rank-2p
update), the few columns between the two free sets added or removed, one Cholesky at our r (``_from_peer``; exact up
to rounding). ``begin`` may also run fewer of its passes now and factor the next pass's S, so that a solve spread
over two frames costs them about the same (docs/performance.md, "the trial from the fit's factor").
"""

from __future__ import annotations

import weakref

import numpy as np
import scipy.linalg as sl
from scipy.linalg.blas import dsymm, dsyr2k, dsyrk
from scipy.linalg.lapack import dpotrf, dpotrs

from solvers.marker_space_kernels import repartition, rhs, x_and_gradient

REFRESH = 1024  # updates of the kept marker-space matrix before it is formed afresh (64: ~1 ms each, the fit's every
# 64th frame, the stream's p99 at 72 x 1000; the weights over 1200 frames the same to 3e-11: docs/performance.md)
WOODBURY = 8  # at most this many columns changed from the kept factor's free set: solved through it, no refactor
FRESH_PASSES = 2  # a bounded solve's passes (frame_passes > 0) from a start that is not this QP's own last stop
PIVOT_BUDGET = 3  # block-pivoting passes without fewer wrong sides before the primal active-set method takes over


class MarkerSpaceQP:
    """One visibility pattern's J, D and limits. ``solve(f, x0)``: the optimum from any start ``x0`` (its
    partition is the first guess), or None where ``max_iter`` passes did not settle (the caller falls back)."""

    def __init__(self, J: np.ndarray, d: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                 max_iter: int = 200, whole: tuple[MarkerSpaceQP, np.ndarray] | None = None,
                 same: MarkerSpaceQP | None = None) -> None:
        """Raises ``np.linalg.LinAlgError`` where the columns with d = 0 are not fixed by J (e.g. too few markers
        seen for the pose) and ``ValueError`` for a d = 0 column with a limit. ``whole``: this QP on a superset of
        J's rows with the same d (the pattern with every marker seen) and our rows' indices in its rows: S of every
        column free is then its block with the pose projected off (``_from_peer``'s identity) instead of an r x r x n
        product (a pattern with markers hidden, issue 39). ``same``: this QP on the same J at another d with the
        same d = 0 columns (another prior strength): its arrays that do not depend on d are read, not copies made
        (one J in the caches for every strength's trial on a fold, issue 39)."""
        J = np.asarray(J, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64).reshape(-1)
        self.r, n = J.shape
        lower = np.asarray(lower, dtype=np.float64).reshape(n)
        upper = np.asarray(upper, dtype=np.float64).reshape(n)
        if d.shape != (n,) or np.any(d < 0) or not np.isfinite(d).all():
            raise ValueError(f"d must be {n} finite values >= 0")
        self.P, self.G = np.flatnonzero(d == 0), np.flatnonzero(d > 0)
        if np.isfinite(lower[self.P]).any() or np.isfinite(upper[self.P]).any():
            raise ValueError("a variable without curvature of its own (d = 0) must be unbounded")
        if same is not None and np.array_equal(same.P, self.P) and np.array_equal(same.G, self.G) \
                and np.array_equal(same._J_given, J):
            self._J_given, self._C, self._A, self._Q, self.J = same._J_given, same._C, same._A, same._Q, same.J
            self._JP = same._JP
        else:
            self._J_given = J
            JG = J[:, self.G]
            self._C = self._A = self._JP = None
            if len(self.P):  # x_P = -C^-1 (J_P'J_G x_G + f_P), C = J_P'J_P
                JP = self._JP = np.ascontiguousarray(J[:, self.P])
                self._C = sl.cho_factor(JP.T @ JP)
                if np.diagonal(self._C[0]).min() <= 1e-9 * np.sqrt(np.abs(np.diagonal(JP.T @ JP)).max()):
                    raise np.linalg.LinAlgError("the unpenalised columns are not fixed by the seen rows")
                self._A = sl.cho_solve(self._C, JP.T @ JG)
                JG = JG - JP @ self._A
            # range(J_P), orthonormal: projected off a peer's S (``near``)
            self._Q = np.asfortranarray(np.linalg.qr(JP)[0]) if len(self.P) else None
            self.J = np.ascontiguousarray(JG)
        self.d = d[self.G]
        self.dinv = 1.0 / self.d
        self.lo, self.hi = lower[self.G], upper[self.G]
        self.max_iter = int(max_iter)
        self.iterations = 0
        # rows: the columns of J D^-1/2 (W[:, idx] = _Wt[idx].T), each contiguous: a refactor gathers k of them
        self._Wt = np.ascontiguousarray(self.J.T * np.sqrt(self.dinv)[:, None])
        if whole is not None and self._Q is not None and np.array_equal(whole[0].G, self.G) \
                and np.array_equal(whole[0].d, self.d):
            self._S_all = _projected(whole[0]._S_all, whole[1], self._Q, 1.0)  # (its lower triangle)
        else:
            self._S_all = np.asfortranarray(self._Wt.T @ self._Wt)  # every column free
            self._S_all.flat[:: self.r + 1] += 1.0
        # S of the free set _F (its lower triangle: what LAPACK reads) and its Cholesky factor _L
        self._S, self._F, self._L = self._S_all, np.ones(len(self.G), bool), None
        self._begun: tuple | None = None  # f, x0 and the state of a solve begun (``begin``)
        self._wood: tuple | None = None  # a free set a few columns from _F: (F, U, S^-1 U, LU of the capacitance)
        self._updates = 0
        # the last solve's x, the partition it stopped at, its f and its count of wrong sides (best, budget)
        self._carry: tuple | None = None
        self._near: tuple | None = None  # a peer whose kept S this solve may start from, and our rows in its rows
        self._ratio: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # peer -> d_peer / d, or None

    def data_term(self, v: np.ndarray) -> np.ndarray:
        """J' v for J as given (v on its rows), from the J with the pose projected off that every pass reads, not
        from J or B'M^2: J_G' v = (J_G - J_P A)' v + A' J_P' v. kalman's fit and trial at 72 x 1000 so read one 1.7 MB
        matrix a frame fewer (issue 39; equal to rounding)."""
        out = np.empty(len(self.G) + len(self.P))
        if self._JP is None:
            out[self.G] = self.J.T @ v
            return out
        vP = self._JP.T @ v
        out[self.P] = vP
        out[self.G] = self.J.T @ v + self._A.T @ vP
        return out

    def _solve_S(self, F: np.ndarray, b: np.ndarray) -> np.ndarray:
        """S^-1 b for free set F. Within WOODBURY columns of the kept factor's free set, through that factor and a
        k x k capacitance (Woodbury; the last passes of a solve change 0-3 columns, and a 216 x 216 refactor costs
        ~0.2 ms); otherwise the kept S updated by the changed columns (or formed) and refactored."""
        if self._factor(F):
            return dpotrs(self._L, b, lower=1)[0]
        _, U, Z, M = self._wood
        y = dpotrs(self._L, b, lower=1)[0]
        return y - Z @ sl.lu_solve(M, U.T @ y, check_finite=False)

    def _factor(self, F: np.ndarray) -> bool:
        """Make S of free set F solvable: True where the kept factor is its own (unchanged or refactored), False
        where ``_wood`` holds the Woodbury terms for it."""
        changed = np.flatnonzero(F != self._F)
        if not len(changed) and self._L is not None:
            return True
        if len(changed) > WOODBURY or self._L is None:
            self._refactor(F, changed)
            return True
        if self._wood is None or not np.array_equal(self._wood[0], F):
            U = self._Wt[changed].T  # S_F = S + U C U', C = diag(+1 freed, -1 bounded) = C^-1
            Z = dpotrs(self._L, U, lower=1)[0]
            self._wood = (F.copy(), U, Z, sl.lu_factor(np.diag(np.where(F[changed], 1.0, -1.0)) + U.T @ Z,
                                                      check_finite=False))
        return False

    def _refactor(self, F: np.ndarray, changed: np.ndarray) -> None:
        """S of free set F from the kept one by the changed columns (symmetric rank-k products, lower triangle), or
        formed from all columns' S less the bounded ones' (or the free ones' alone), and its Cholesky factor."""
        n_free = int(np.count_nonzero(F))
        n_bound = len(F) - n_free
        if self._near is not None and self._from_peer(F, min(len(changed), n_bound, n_free)):
            return
        if len(changed) <= min(n_bound, n_free) and self._updates < REFRESH:
            S = self._S.copy(order="F") if self._S is self._S_all else self._S  # updated in place: its last use
            for idx, sign in ((changed[F[changed]], 1.0), (changed[~F[changed]], -1.0)):
                if len(idx):
                    S = dsyrk(sign, self._Wt[idx].T, beta=1.0, c=S, lower=1, overwrite_c=1)
            self._updates += 1
        else:
            if n_bound <= n_free:
                S = dsyrk(-1.0, self._Wt[~F].T, beta=1.0, c=self._S_all.copy(order="F"), lower=1, overwrite_c=1)
            else:
                S = dsyrk(1.0, self._Wt[F].T, beta=1.0, c=np.eye(self.r, order="F"), lower=1, overwrite_c=1)
            self._updates = 0
        L, info = dpotrf(S, lower=1, clean=0)
        if info:
            self._S, self._F, self._L, self._wood = self._S_all, np.ones(len(self.G), bool), None, None
            raise np.linalg.LinAlgError(f"marker-space matrix not positive definite (dpotrf info {info})")
        self._S, self._F, self._L, self._wood = S, F.copy(), L, None

    def ratio(self, peer: MarkerSpaceQP) -> float | None:
        """c = d_peer / d where ``peer`` is this QP on more rows at another scale of D (a prior's strength, no
        floor): the same columns, pose (d = 0) columns and limits, d proportional to rounding. Else None."""
        if peer not in self._ratio:
            c = None
            if (np.array_equal(peer.G, self.G) and np.array_equal(peer.P, self.P) and peer.r >= self.r
                    and np.array_equal(peer.lo, self.lo) and np.array_equal(peer.hi, self.hi) and len(self.G)):
                c = float(np.median(peer.d / self.d))
                c = c if np.allclose(peer.d, c * self.d, rtol=1e-12, atol=0.0) else None
            self._ratio[peer] = c
        return self._ratio[peer]

    def _from_peer(self, F: np.ndarray, own: int) -> bool:
        """S of free set F from the peer's kept S (``near``) where fewer columns separate F from the peer's free set
        than from our own (+ the r^2 work of taking it over): with W = (I - Pi) J D^-1/2 (Pi onto the pose columns'
        range), our rows R of the peer's J and d = d_peer / c, (I - Pi) [(I - Pi_peer) J]_R = (I - Pi) J_R, so

            S_F - I = c (I - Pi) [S_peer,F - I]_RR (I - Pi),

        the peer's block scaled, the pose projected off by a rank-2p update (Pi = Q Q'), then the columns between the
        two free sets by symmetric rank-k products and one Cholesky at our r -- instead of forming S over every free
        column (kalman's held-out trial at 72 x 1000: its own S 90 frames stale, the fit's from this very start)."""
        peer, idx = self._near
        c = self.ratio(peer)
        if c is None or peer._L is None:
            return False
        changed = np.flatnonzero(F != peer._F)
        if len(changed) + len(self.P) >= own:
            return False
        if self._Q is None or len(idx) == peer.r:  # (the peer's rows: its S already projected off our pose's range)
            S = np.take(peer._S.T[idx], idx, axis=1).T  # Fortran order; its lower triangle the peer's (LAPACK's)
            S *= c
            S.T.flat[:: self.r + 1] += 1.0 - c
        else:
            S = _projected(peer._S, idx, self._Q, c)
        for cols, sign in ((changed[F[changed]], 1.0), (changed[~F[changed]], -1.0)):
            if len(cols):
                S = dsyrk(sign, self._Wt[cols].T, beta=1.0, c=S, lower=1, overwrite_c=1)
        L, info = dpotrf(S, lower=1, clean=0)
        if info:
            return False
        self._S, self._F, self._L, self._wood = S, F.copy(), L, None
        self._updates = min(peer._updates + 1, REFRESH)
        return True

    def _same_rows_stop(self, x0: np.ndarray) -> tuple | None:
        """The peer's last stop (``_carry``) where the peer (``near``) is this QP on the same rows at another scale of
        D and stopped at ``x0``; else None."""
        if self._near is None:
            return None
        peer, idx = self._near
        c = peer._carry
        if len(idx) != peer.r or c is None or not np.array_equal(c[0], x0) or self.ratio(peer) is None:
            return None
        return c

    def _subproblem(self, fG: np.ndarray, at_lo: np.ndarray, at_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The minimiser with the bounded weights held at their limits (x) and the gradient there (0 on F)."""
        y = self._solve_S(~(at_lo | at_hi), self.J @ rhs(fG, self.dinv, self.lo, self.hi, at_lo, at_hi))
        return x_and_gradient(self.J.T @ y, fG, self.d, self.dinv, self.lo, self.hi, at_lo, at_hi)

    def begin(self, f: np.ndarray, x0: np.ndarray, passes: int, frame_passes: int = 0,
              near: tuple[MarkerSpaceQP, np.ndarray] | None = None, now: int | None = None) -> None:
        """The first ``passes`` passes of ``solve(f, x0, frame_passes)`` now; that solve next continues where they
        stopped (the same passes in the same order, so the same x): one solve spread over two frames. ``now``: of
        those passes only this many here, and the S of the next one factored (its first step); the solve then runs
        the rest as well (the same x, the work shared more evenly between the frames). ``near``: a peer (this QP on
        a superset of its rows, D scaled: ``ratio``) and the indices of our rows in its rows, whose kept S a
        refactor here may start from (``_from_peer``; the same x up to rounding)."""
        f, x0 = np.array(f, dtype=np.float64), np.array(x0, dtype=np.float64)
        passes = min(int(passes), self.max_iter)
        now = passes if now is None else min(int(now), passes)
        self._begun = None
        self._near = near
        try:
            state = self._pivot(f, x0, now, frame_passes=frame_passes)
            if not isinstance(state[0], str):
                self._factor(~(state[0] | state[1]))
        finally:
            self._near = None
        self._begun = (f, x0, state, passes - now if frame_passes else 0)

    def solve(self, f: np.ndarray, x0: np.ndarray, frame_passes: int = 0,
              near: tuple[MarkerSpaceQP, np.ndarray] | None = None) -> np.ndarray | None:
        """The optimum from ``x0`` (None where ``max_iter`` passes did not settle); with ``frame_passes`` > 0 at most
        that many passes, the clipped point where they did not settle, the next solve from it going on (the
        real-time iteration above). ``near``: as for ``begin``."""
        f, x0 = np.asarray(f, dtype=np.float64), np.asarray(x0, dtype=np.float64)
        begun, self._begun = self._begun, None
        state = None
        if begun is not None and np.array_equal(begun[0], f) and np.array_equal(begun[1], x0):
            state = begun[2]
        if state is None or not isinstance(state[0], str):
            self._near = near
            try:
                state = self._pivot(f, x0, self.max_iter, state, frame_passes + (begun[3] if state else 0))
            finally:
                self._near = None
        return state[1]

    def _pivot(self, f: np.ndarray, x0: np.ndarray, stop: int, state: tuple | None = None,
               frame_passes: int = 0) -> tuple:
        """Block-pivoting passes up to pass ``stop``: ("done", x or None) where they settled, handed over to the
        primal method or ran out of ``max_iter``; else the state to continue from."""
        fG = f[self.G] if self._C is None else f[self.G] - self._A.T @ f[self.P]
        passes = int(frame_passes)
        if state is None:
            x = x0[self.G]
            state = (x <= self.lo, x >= self.hi, len(x) + 1, PIVOT_BUDGET, 0)
            c = self._carry
            if passes and c is not None and np.array_equal(c[0], x0):
                # the same QP again (a still take): its count of wrong sides goes on, so that a block-pivoting
                # cycle is handed to the primal method as in one solve; new data: counted afresh
                same = np.array_equal(c[3], f)
                state = (c[1], c[2], c[4] if same else len(x) + 1, c[5] if same else PIVOT_BUDGET, 0)
            elif passes and (peer := self._same_rows_stop(x0)) is not None:
                # this QP at another strength where it stopped (kalman's fit on a strength switch): the peer's last
                # partition is as near this optimum as our own would be after a frame, so one pass (the real-time
                # iteration) as on any frame, its S the peer's scaled (``_from_peer``)
                state = (peer[1].copy(), peer[2].copy(), len(x) + 1, PIVOT_BUDGET, 0)
            elif passes:
                # another start (another visibility pattern's or strength's x): its clipped point holds the weights
                # its last pass freed at their limits; one more pass frees them again, so they are not lost
                passes = max(passes, FRESH_PASSES)
        self._carry = None
        limit = state[4] + passes if passes and stop == self.max_iter else self.max_iter
        at_lo, at_hi, best, budget, it = state
        while it < stop:
            it += 1
            x, g = self._subproblem(fG, at_lo, at_hi)
            lo1, hi1, wrong = repartition(x, g, self.lo, self.hi, at_lo, at_hi)
            if not wrong:  # settled: the optimum, and the partition the next frame's solve goes on from
                x = self._full(x, f)
                self._carry, self.iterations = (x, at_lo, at_hi, f.copy(), 0, PIVOT_BUDGET), it
                return "done", x
            if wrong < best:
                best, budget = wrong, PIVOT_BUDGET
            else:
                budget -= 1
            if budget <= 0:
                return "done", self._primal(fG, f, np.minimum(np.maximum(x, self.lo), self.hi), it)
            at_lo, at_hi = lo1, hi1
            if it >= limit:  # unsettled: the clipped point now, the next solve from this partition
                x = self._full(np.minimum(np.maximum(x, self.lo), self.hi), f)
                self._carry, self.iterations = (x, at_lo, at_hi, f.copy(), best, budget), it
                return "done", x
        if it >= self.max_iter:
            self.iterations = self.max_iter
            return "done", None
        return at_lo, at_hi, best, budget, it

    def _primal(self, fG: np.ndarray, f: np.ndarray, x: np.ndarray, it: int) -> np.ndarray | None:
        """The primal active-set method from the feasible ``x``: a step towards the subproblem's minimiser until
        a limit blocks, or the bounded weight with the most wrong multiplier freed; the objective falls at every
        step, so it terminates (Nocedal & Wright 2006 §16.5)."""
        at_lo, at_hi = x <= self.lo, x >= self.hi
        while it < self.max_iter:
            it += 1
            xs, g = self._subproblem(fG, at_lo, at_hi)
            p = xs - x
            F = ~(at_lo | at_hi)
            with np.errstate(divide="ignore", invalid="ignore"):
                room = np.where(p < 0, (self.lo - x) / p, np.where(p > 0, (self.hi - x) / p, np.inf))
            room[~F] = np.inf
            j = int(np.argmin(room))
            if room[j] < 1.0:  # a limit blocks: step to it and bound it
                x = x + max(room[j], 0.0) * p
                x[j] = self.lo[j] if p[j] < 0 else self.hi[j]
                at_lo[j], at_hi[j] = p[j] < 0, p[j] > 0
                continue
            x = xs
            push = np.where(at_lo, -g, np.where(at_hi, g, 0.0)) * np.sqrt(self.dinv)  # > 0: wants inside
            j = int(np.argmax(push))
            if push[j] <= 0:
                x = self._full(x, f)
                self._carry, self.iterations = (x, at_lo, at_hi, f.copy(), 0, PIVOT_BUDGET), it
                return x
            at_lo[j] = at_hi[j] = False
        self.iterations = self.max_iter
        return None

    def _full(self, xG: np.ndarray, f: np.ndarray) -> np.ndarray:
        out = np.empty(len(self.G) + len(self.P))
        out[self.G] = xG
        if self._C is not None:
            # (LAPACK's own call: scipy's cho_solve checks finiteness, ~13 of its ~14 µs; the same numbers)
            out[self.P] = -(self._A @ xG + dpotrs(self._C[0], f[self.P], lower=self._C[1])[0])
        return out


def _projected(S: np.ndarray, idx: np.ndarray, Q: np.ndarray, c: float) -> np.ndarray:
    """c (P S_RR P - P) + I, P = I - Q Q' (Q orthonormal), from the lower triangle of S (``idx``: the rows R), into the
    lower triangle of a new Fortran-order matrix: c S - c (Q V' + V Q') + (1 - c) I, V = S Q - Q (Q'S Q) / 2 - Q / 2
    (a symmetric rank-2p update)."""
    S = np.take(S.T[idx], idx, axis=1).T  # Fortran order; its lower triangle S's (LAPACK's)
    Y = dsymm(1.0, S, Q, lower=1)
    S = dsyr2k(-c, Q, Y - 0.5 * Q @ (Q.T @ Y + np.eye(Q.shape[1])), beta=c, c=S, lower=1, overwrite_c=1)
    S.T.flat[:: len(idx) + 1] += 1.0 - c
    return S
