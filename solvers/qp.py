"""Per-frame bounded quadratic programme for blendshape weights (Curio et al. 2006 §2.3).

Curio et al. fit each frame's markers by "quadratic programming enforcing positivity constraints
on the morph weights"; Lewis et al. 2014 §5.2 note this is the standard constrained linear problem
for mocap-driven rigs. Per frame:

    minimise  |M (B w - s)|^2 + lam |w|^2 + gam |w - w_prev|^2 + alpha (w - mu)' P (w - mu)
    subject to lower <= w <= upper,

M a per-marker weight (confidence), the last two terms an optional temporal term and Gaussian
prior. The Hessian H = B'M^2B + (lam + gam) I + alpha P is constant, so each marker-visibility
pattern gets one workspace (H formed once; only the linear term changes per frame), solved by the
warm-started primal active-set method of ``solvers.box_qp`` on the free weights: the previous
frame's free set and the Cholesky factor of its block carry over, so a frame costs O(m 3n) for the
linear term plus O(k m) for the optimality check (k free weights). DAQP (the fastest general library in
benchmarks/qp_libraries.py) takes over, warm, where the active set moves by many weights a frame
and hundreds of weights are free (its factor updates beat refactoring there), and if the active-set
solve fails.
Missing markers drop their rows (a new pattern's H is the all-markers H downdated by them);
workspaces are cached per visibility pattern in a bounded LRU.
"""

from __future__ import annotations

import hashlib
import logging
import math
import threading
import weakref
from collections import OrderedDict

import numpy as np

from solvers.box_qp import BoxQP
from solvers.marker_space_qp import MarkerSpaceQP
from solvers.qp_kernels import pattern_hessian, pattern_workspace, smallest_eigenvalue

log = logging.getLogger(__name__)


# the marker-space path when the shapes number at least this many times the marker coordinates (72 x 1000: 4.7;
# 72 x 150 and ICT's ~53 shapes stay in weight space)
MARKER_SPACE_RATIO = 2.0
# this thread's last marker-space solves, newest first: (basis, row weights, rows, its MarkerSpaceQP; basis and solver
# by weak reference), the peers a solve from one's stop may start its refactor from (``FrameQP._near``)
_STOPS = threading.local()
_STOPS_KEPT = 4
_LAMBDA_MIN_SIZE = 256
_LAMBDA_MIN: dict[bytes, float] = {}  # smallest eigenvalue per matrix content: FrameQPs at several strengths share one


def _lambda_min(A: np.ndarray) -> float:
    """Smallest eigenvalue of the symmetric ``A``, cached by content (an eigensolve at a 1000-shape rig)."""
    if not A.size:
        return np.inf
    diag = np.diagonal(A)
    if not np.any(A - np.diag(diag)):
        return float(diag.min())
    key = hashlib.blake2b(np.ascontiguousarray(A).tobytes(), digest_size=16).digest() + bytes(str(A.shape), "ascii")
    if key not in _LAMBDA_MIN:
        if len(_LAMBDA_MIN) >= _LAMBDA_MIN_SIZE:  # a batch over many actors' profiles: keep the cache bounded
            _LAMBDA_MIN.clear()
        _LAMBDA_MIN[key] = float(np.linalg.eigvalsh(A)[0])
    return _LAMBDA_MIN[key]


class _CondBound:
    """A lower bound on lambda_min(H), H = J'J + C, J the seen rows of the (marker-weighted) basis, C fixed,
    zero on the rows and columns of the unpenalised variables U (the pose columns of solvers.pose_refine) and
    >= c on the rest S: with s^2 = lambda_min(H_UU) (how well the seen markers fix U) and b = ||J_S|| <= the
    all-markers norm, z'Hz >= c|z_S|^2 + max(0, s|z_U| - b|z_S|)^2 >= c s^2 / (c + b^2 + s^2) |z|^2 (the
    2 x 2 matrix [[c + b^2, -s b], [-s b, s^2]]'s determinant over its trace). With trace(H) >= lambda_max
    it bounds cond(H) with one |U| x |U| eigensolve (compiled) per visibility pattern instead of a Cholesky of H;
    with U empty it is c (a ridge or full prior)."""

    def __init__(self, const: np.ndarray, weighted_basis: np.ndarray) -> None:
        free = ~np.any(const, axis=1)
        self.U, S = np.flatnonzero(free), np.flatnonzero(~free)
        contiguous = len(self.U) and self.U[-1] - self.U[0] == len(self.U) - 1
        self._block = (slice(self.U[0], self.U[-1] + 1),) * 2 if contiguous else np.ix_(self.U, self.U)
        # the block as a range, for the compiled pattern kernel (solvers.qp_kernels.pattern_hessian); None if not one
        self.span = (int(self.U[0]), int(self.U[-1]) + 1) if contiguous else (0, 0) if not len(self.U) else None
        self.c = _lambda_min(const[np.ix_(S, S)]) if len(S) else 0.0
        self.b2 = 0.0
        if len(self.U) and self.c > 0:
            JS = weighted_basis[:, S]
            self.b2 = float(np.linalg.eigvalsh(JS @ JS.T if JS.shape[0] < JS.shape[1] else JS.T @ JS)[-1])

    def lambda_min(self, H: np.ndarray) -> float:
        if not self.c > 0:
            return 0.0
        if not len(self.U):
            return self.c
        return self.from_block(smallest_eigenvalue(np.ascontiguousarray(H[self._block])))

    def from_block(self, s2: float) -> float:
        """The bound from s^2, the smallest eigenvalue of H's U block."""
        if not self.c > 0:
            return 0.0
        if not len(self.U):
            return self.c
        return self.c * s2 / (self.c + self.b2 + s2) if s2 > 0 else 0.0


class _Workspace:
    """One visibility pattern: H, the linear-term matrix, the active-set solver and DAQP, each built on
    first use (with many markers missing most patterns are seen once, often while DAQP has taken over)."""

    __slots__ = ("_H", "_make", "floor", "rows", "_limits", "_box", "_daqp", "marker_space")

    def __init__(self, H: np.ndarray | None, floor: float, rows: np.ndarray | None, limits: tuple,
                 make=None) -> None:
        """``H`` None: ``make()`` forms it on first use (a marker-space pattern, whose solve does not read it)."""
        self._H, self._make, self.floor, self.rows = H, make, floor, rows
        self._limits = limits  # lower, upper and BoxQP.limit_rows of them: shared by every pattern
        self._box: BoxQP | None = None
        self._daqp = None
        self.marker_space: MarkerSpaceQP | None | bool = None  # built on first use; False where it cannot be

    @property
    def H(self) -> np.ndarray:
        if self._H is None:
            self._H, self._make = self._make(), None
        return self._H

    @property
    def box(self) -> BoxQP:
        if self._box is None:
            lower, upper, limit_rows = self._limits
            self._box = BoxQP(self.H, lower, upper, limit_rows=limit_rows)
        return self._box

    def daqp(self, f: np.ndarray, lower: np.ndarray, upper: np.ndarray,
             sense: np.ndarray | None) -> tuple[np.ndarray | None, int]:
        """DAQP on this H (workspace built on first use), warm from its own last active set or ``sense``."""
        import daqp

        if self._daqp is None:
            self._daqp = daqp.Model()
            m = len(f)
            self._daqp.setup(self.H, np.zeros(m), np.zeros((0, m)), upper.copy(), lower.copy())
            sense = np.zeros(m, dtype=np.int32) if sense is None else sense
        if sense is None:
            self._daqp.update(f=f)
        else:
            self._daqp.update(f=f, sense=sense)
        x, _, flag, info = self._daqp.solve()
        ok = flag > 0 and np.isfinite(x).all()
        return (np.minimum(np.maximum(x, lower), upper) if ok else None), int(info["iterations"])


class FrameQP:
    """Streaming per-frame QP. ``step(target (n,3), valid (n,)) -> weights (m,)``; never raises."""

    def __init__(self, basis: np.ndarray, lower: np.ndarray, upper: np.ndarray, ridge: float = 0.0,
                 temporal: float = 0.0, marker_weights: np.ndarray | None = None,
                 prior: tuple[np.ndarray, np.ndarray] | None = None, prior_weight: float = 0.0,
                 cache_size: int = 32, like: FrameQP | None = None, frame_passes: int = 0) -> None:
        """``like``: a FrameQP on the same basis and marker weights (kalman's fit at another prior strength) whose
        B'M^2 this one reads instead of a copy of its own: a frame reads all of it, and a fit that takes over from
        another found its copy out of the caches (issue 39). ``frame_passes``: where a frame is solved in marker
        space, at most that many block-pivoting passes a ``step`` (the real-time iteration of
        solvers.marker_space_qp; 0: every frame to its optimum); ``step_take`` always solves to the optimum."""
        self.basis = np.asarray(basis, dtype=np.float64)
        if self.basis.ndim != 2 or self.basis.shape[0] % 3:
            raise ValueError(f"basis must be 3n x m, got {self.basis.shape}")
        self.n, self.m = self.basis.shape[0] // 3, self.basis.shape[1]
        self.lower = np.asarray(lower, dtype=np.float64).reshape(self.m)
        self.upper = np.asarray(upper, dtype=np.float64).reshape(self.m)
        if np.any(self.lower > self.upper):
            raise ValueError("lower bound above upper bound")
        if ridge < 0 or temporal < 0 or prior_weight < 0:
            raise ValueError("ridge, temporal and prior weights must be >= 0")
        self.ridge, self.temporal = float(ridge), float(temporal)
        mw = np.ones(self.n) if marker_weights is None else np.asarray(marker_weights, dtype=np.float64)
        if mw.shape != (self.n,) or np.any(mw < 0) or not np.isfinite(mw).all():
            raise ValueError(f"marker_weights must be {self.n} finite values >= 0")
        self._row_w = np.repeat(mw**2, 3)  # M^2 on the rows x0 y0 z0 x1 ...
        if like is not None and like.basis is self.basis and np.array_equal(like._row_w, self._row_w):
            self._BtD = like._BtD
            self._marker_J = like._marker_J
        else:
            self._BtD = (self.basis * self._row_w[:, None]).T.copy()  # m x 3n, B'M^2
            # rows -> a marker-space solver on them (any strength): its d-free arrays shared (MarkerSpaceQP ``same``)
            self._marker_J: weakref.WeakValueDictionary = weakref.WeakValueDictionary()
        self._const = (self.ridge + self.temporal) * np.eye(self.m)
        self._prior_f = None
        if prior is not None and prior_weight > 0:
            mu, P = (np.asarray(a, dtype=np.float64) for a in prior)
            self._const = self._const + prior_weight * P
            self._prior_f = prior_weight * P @ mu
        # Unobserved shapes (all their markers missing) make H singular; a tiny pull towards the
        # previous weights keeps it positive definite and holds those shapes where they were.
        scale = float(np.mean(np.einsum("ij,ij->j", self.basis, self.basis))) or 1.0
        self._floor = 1e-9 * scale
        self._cond = _CondBound(self._const, self.basis * np.sqrt(self._row_w)[:, None])
        self._H_all: np.ndarray | None = None  # H with every marker seen; other patterns downdate it
        self._limits: tuple | None = None
        self.linear = np.zeros(self.m)  # a linear term callers may change per frame (e.g. an L1 penalty)
        self.cache_size = int(cache_size)
        self.frame_passes = int(frame_passes)
        self._begun_f: tuple | None = None  # ``begin``'s workspace, coordinates, linear term and f
        self._models: OrderedDict[bytes, _Workspace] = OrderedDict()
        self._all_seen = np.ones(self.n, bool).tobytes()
        self._all_rows = np.ones(3 * self.n, bool)
        self._prior_term = np.zeros(self.m) if self._prior_f is None else self._prior_f
        self.failures = 0
        self.iterations = 0  # active-set passes (DAQP: iterations) of the last solve
        # far more weights than marker coordinates, and D + J'J with D diagonal (a ridge or diagonal prior): while
        # the last solution has at least as many weights free as there are marker coordinates (kalman's fit at
        # 72 x 1000; not the qp mode's sparse one there) the frame is solved in marker space (docs/performance.md,
        # "`kalman` at 72 x 1000")
        d = np.diagonal(self._const)
        self.marker_space = bool(self.m >= MARKER_SPACE_RATIO * 3 * self.n and not np.any(self._const - np.diag(d))
                                 and np.all((d > 0) | ~(np.isfinite(self.lower) | np.isfinite(self.upper))))
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        self._prev = np.clip(np.zeros(self.m), self.lower, self.upper)
        self._last_key: bytes | None = None  # pattern of the last successful solve: its solver is warm
        self._daqp_key: bytes | None = None  # the same for DAQP (used while the active set churns)
        self.churn = 1.0  # running mean of self.iterations: how much the active set moves per frame

    def warm(self, x: np.ndarray) -> None:
        """Start the next solve from ``x`` (clipped to the limits), e.g. a nearby problem's solution. Not where
        hundreds of weights were free: a nearer start lowers the churn that hands such solves to DAQP, and the box
        QP's passes on them cost more than DAQP's (kalman's trials at 72 x 1000, docs/performance.md
        "`kalman`'s streamed step"); there the marker-space path takes the start whatever it is."""
        ws = getattr(self, "_last_ws", None)
        if not self.marker_space and (self._daqp_key is not None or (ws is not None and ws._box is not None
                                                                     and len(ws.box.F) >= self._FREE_DAQP)):
            return
        self._prev = np.minimum(np.maximum(np.asarray(x, dtype=np.float64), self.lower), self.upper)
        self._last_key = None

    @property
    def cached_patterns(self) -> int:
        return len(self._models)

    def knows(self, valid: np.ndarray) -> bool:
        """Whether a step on this visibility pattern finds its workspace built (its cost is then the solve)."""
        key = np.asarray(valid, dtype=bool).reshape(-1).tobytes()
        return key == self._last_key or key == self._daqp_key or key in self._models

    def prepare(self, valid: np.ndarray) -> None:
        """Build this pattern's workspace now (H downdated, its condition check, the box QP's state), so that the
        frame that steps on it pays only its solve: kalman builds the next frame's, which its marker filter's one
        frame of lag makes known a frame ahead (issue 39)."""
        seen = np.asarray(valid, dtype=bool).reshape(-1)
        key = seen.tobytes()
        if seen.shape[0] != self.n or not seen.any() or key in self._models:
            return
        ws = self._workspace(key, seen)
        if not self.marker_space:
            ws.box  # noqa: B018 - built on first use; here, not on the step's frame

    def _workspace(self, key: bytes, seen: np.ndarray) -> _Workspace:
        ws = self._models.get(key)
        if ws is not None:
            self._models.move_to_end(key)
            return ws
        if self._H_all is None:
            self._H_all = self.basis.T @ (self.basis * self._row_w[:, None]) + self._const
        if self._limits is None:
            self._limits = (self.lower, self.upper, BoxQP.limit_rows(self.lower, self.upper, self.m))
        n_miss = 3 * (self.n - int(np.count_nonzero(seen)))
        if 0 < n_miss <= 3 * self.n // 2 and self._cond.span is not None and not self.marker_space:
            return self._downdated(key, seen)  # the whole workspace in one compiled call
        rows = np.repeat(seen, 3)
        bound = None
        if n_miss == 0:
            H = self._H_all
        elif n_miss <= len(rows) // 2 and self._cond.span is not None:  # marker space, a few markers missing
            trace, s2 = self._pattern_bounds(rows)
            bound = self._cond.from_block(s2)
            if not trace > 1e12 * bound:  # no floor: H (m x m) formed only if a solve reads it
                return self._cached(key, _Workspace(None, 0.0, rows, self._limits, lambda: self._pattern_H(seen)))
            H = self._pattern_H(seen)
        elif n_miss <= len(rows) // 2:
            miss = ~rows
            Bm = self.basis[miss]
            H = self._H_all - Bm.T @ (Bm * self._row_w[miss, None])
        else:
            Bv = self.basis[rows]
            H = Bv.T @ (Bv * self._row_w[rows, None]) + self._const
        if bound is None:
            trace, bound = np.trace(H), self._cond.lambda_min(H)
        H, floor = self._floored(H, trace, bound)
        return self._cached(key, _Workspace(H, floor, None if n_miss == 0 else rows, self._limits))

    def _pattern_H(self, seen: np.ndarray) -> np.ndarray:
        """H of a pattern missing a few markers: a rank-3k downdate, O(k m^2) not O(n m^2), in one compiled call."""
        H = np.empty_like(self._H_all)
        pattern_hessian(self._H_all, self.basis, self._row_w, seen, *self._cond.span, H)
        return H

    def _pattern_bounds(self, rows: np.ndarray) -> tuple[float, float]:
        """trace(H) and the smallest eigenvalue of H's pose block for the pattern of ``rows``, without H: at 72 x 1000
        the downdate of H is ~27 ms a new pattern (a trial's training pattern with markers hidden), these ~0.1 ms."""
        miss = ~rows
        w = self._row_w[miss]
        Bm = self.basis[miss]
        trace = float(np.trace(self._H_all) - np.einsum("ij,ij,i->", Bm, Bm, w))
        u0, u1 = self._cond.span
        if u1 <= u0:
            return trace, np.inf
        Bu = Bm[:, u0:u1]
        return trace, smallest_eigenvalue(np.ascontiguousarray(self._H_all[u0:u1, u0:u1] - Bu.T @ (Bu * w[:, None])))

    def _floored(self, H: np.ndarray, trace: float, bound: float) -> tuple[np.ndarray, float]:
        """H with the floor it needs, and that floor (0 where its condition is fine)."""
        if trace > 1e12 * bound:
            try:  # (max / min Cholesky diagonal)^2 bounds cond(H) from below: no SVD per new pattern
                d = np.diagonal(np.linalg.cholesky(H))
                if d.min() <= 0 or (d.max() / d.min()) ** 2 > 1e12:
                    raise np.linalg.LinAlgError
            except np.linalg.LinAlgError:
                return H + self._floor * np.eye(self.m), self._floor
        return H, 0.0

    def _cached(self, key: bytes, ws: _Workspace) -> _Workspace:
        self._models[key] = ws
        if len(self._models) > self.cache_size:
            self._models.popitem(last=False)
        return ws

    def _downdated(self, key: bytes, seen: np.ndarray) -> _Workspace:
        """A pattern missing a few markers, in weight space: H downdated, its condition's numbers and the box QP's
        state in one compiled call (solvers.qp_kernels.pattern_workspace; issue 39)."""
        rows, H, trace, s2, *box = pattern_workspace(self._H_all, self.basis, self._row_w, seen, *self._cond.span,
                                                     self._limits[2])
        H, floor = self._floored(H, trace, self._cond.from_block(s2))
        ws = _Workspace(H, floor, rows, self._limits)
        if not floor:  # (a floored H: its solver built on first use, for H as floored)
            ws._box = BoxQP.from_state(H, *box)
        return self._cached(key, ws)

    # ------------------------------------------------------------------ per frame
    def _update_linear(self) -> None:
        """Set ``linear`` for the coming frame from the state (subclasses: e.g. a hysteresis L1 term)."""

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        self._update_linear()
        s = np.asarray(target, dtype=np.float64).reshape(-1)
        seen = np.asarray(valid, dtype=bool).reshape(-1)
        if s.shape[0] != 3 * self.n or seen.shape[0] != self.n:
            log.warning("frame has %d coordinates / %d flags, expected %d markers: holding the last weights",
                        s.shape[0], seen.shape[0], self.n)
            return self._prev.copy()
        key = seen.tobytes()
        if not math.isfinite(np.add.reduce(s)):  # a NaN or inf coordinate (or overflow): drop those markers
            seen = seen & np.isfinite(s.reshape(self.n, 3)).all(axis=1)
            key = seen.tobytes()
        ws = self._frame_workspace(key, seen)
        if ws is None:
            return self._prev.copy()
        return self._advance(key, ws, None, np.ascontiguousarray(s)).copy()

    def step_take(self, targets: np.ndarray, valid: np.ndarray, block: int = 1024) -> np.ndarray:
        """``step`` over every frame of a take in order (T x m weights): the data term B'M^2 s of a block of
        frames is one matrix product instead of one per frame (the same numbers up to summation order)."""
        T = len(targets)
        S = np.asarray(targets, dtype=np.float64).reshape(T, -1)
        seen_all = np.asarray(valid, dtype=bool).reshape(T, -1)
        W = np.empty((T, self.m))
        if S.shape[1] != 3 * self.n or seen_all.shape[1] != self.n:
            for t in range(T):
                W[t] = self.step(S[t], seen_all[t])
            return W
        keys = [row.tobytes() for row in seen_all]
        passes, self.frame_passes = self.frame_passes, 0  # offline: no frame deadline, every frame to its optimum
        try:
            self._step_blocks(S, seen_all, keys, W, block)
        finally:
            self.frame_passes = passes
        return W

    def _step_blocks(self, S: np.ndarray, seen_all: np.ndarray, keys: list[bytes], W: np.ndarray, block: int) -> None:
        T = len(S)
        for b in range(0, T, block):
            e = min(T, b + block)
            D = np.where(np.repeat(seen_all[b:e], 3, axis=1), S[b:e], 0.0) @ self._BtD.T
            finite = np.isfinite(D).all(axis=1)
            for t in range(b, e):
                if not finite[t - b]:
                    W[t] = self.step(S[t], seen_all[t])
                    continue
                self._update_linear()
                ws = self._frame_workspace(keys[t], seen_all[t])
                W[t] = self._prev if ws is None else self._advance(keys[t], ws, D[t - b])

    def _frame_workspace(self, key: bytes, seen: np.ndarray) -> _Workspace | None:
        """The workspace of this frame's pattern (None when no marker is seen: hold the weights)."""
        if key == self._last_key or key == self._daqp_key:
            return self._last_ws
        if key != self._all_seen and not seen.any():
            return None
        return self._workspace(key, seen)

    def _advance(self, key: bytes, ws: _Workspace, data: np.ndarray | None, s: np.ndarray | None = None) -> np.ndarray:
        """Solve the frame whose data term is ``data`` = B'M^2 s (not kept), or with ``data`` None the frame of
        coordinates ``s`` (its data term formed in the box QP's compiled call), and make it the previous frame."""
        x, f = self._solve(key, ws, None if data is None else self._linear_term(ws, data), s)
        if x is None:
            self.failures += 1
            x = self._fallback(ws, f)
        self._prev = x
        return x

    # Where the active set moves a lot per frame and hundreds of weights are free (an unregularised fit
    # of noisy markers at 1000 shapes), each of BoxQP's passes refactors a block of O(k^3) while DAQP,
    # a dual method whose work grows with the *bounded* weights, updates its factors: above a running
    # mean of 3 iterations per frame with at least _FREE_DAQP weights free, DAQP (warm) takes over;
    # below 2, BoxQP takes back. Measured (docs/performance.md, "Compiled kernels (numba)"): the
    # compiled BoxQP is faster than DAQP at k = 76-169 free weights (at 34 at p50 only), ~100x slower at 367
    # (measured before it kept the factor rows a change leaves; 256 lies untested between 169 and 367).
    _CHURN_DAQP, _CHURN_BOX, _FREE_DAQP = 3.0, 2.0, 256

    def _linear_term(self, ws: _Workspace, data: np.ndarray) -> np.ndarray:
        f = np.subtract(self.linear, data)
        if self._prior_f is not None:
            f -= self._prior_f
        if self.temporal + ws.floor > 0:
            f -= (self.temporal + ws.floor) * self._prev
        return f

    def _solve(self, key: bytes, ws: _Workspace, f: np.ndarray | None,
               s: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray]:
        """The frame's solution (None on failure) and its linear term (``f``, or formed from ``s``)."""
        x = None
        if self.marker_space and np.count_nonzero((self._prev > self.lower) & (self._prev < self.upper)) >= 3 * self.n:
            x, f = self._solve_marker_space(ws, f, s)
            if x is not None:
                self._last_key, self._daqp_key, self._last_ws = key, None, ws
                return x, f
        if self._daqp_key is not None:
            use_daqp = self.churn > self._CHURN_BOX
        else:
            use_daqp = self.churn > self._CHURN_DAQP and len(ws.box.F) >= self._FREE_DAQP
        if not use_daqp:
            restart = key != self._last_key  # another pattern's solver: start it from where we are
            if f is None:
                f = np.empty(self.m)
                x = ws.box.solve_frame(self._BtD, s, self._all_rows if ws.rows is None else ws.rows,
                                       np.asarray(self.linear, dtype=np.float64), self._prior_term,
                                       self.temporal + ws.floor, self._prev, restart, f)
            else:
                if restart:
                    ws.box.warm(self._prev)
                x = ws.box.solve(f)
            self.iterations = ws.box.iterations
            self._last_key, self._daqp_key = (None if x is None else key), None
        if x is None:
            if f is None:
                f = self._linear_term(ws, self._BtD @ (s if ws.rows is None else np.where(ws.rows, s, 0.0)))
            sense = None
            if key != self._daqp_key:  # DAQP constraint states: active (1), at the lower bound (2)
                sense = np.where(self._prev <= self.lower, 3, np.where(self._prev >= self.upper, 1, 0)).astype(np.int32)
            try:
                x, self.iterations = ws.daqp(f, self.lower, self.upper, sense)
            except Exception as exc:  # noqa: BLE001 - a stream must survive a solver failure
                log.debug("daqp failed: %s", exc)
            self._daqp_key = None if x is None else key
            self._last_key = None
        self.churn += 0.1 * (self.iterations - self.churn)
        if x is not None:
            self._last_ws = ws
        return x, f

    def _solve_marker_space(self, ws: _Workspace, f: np.ndarray | None,
                            s: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray]:
        """The frame on this pattern's MarkerSpaceQP (built on first use), or None: the weight-space path then."""
        self._build_marker_space(ws)
        begun, self._begun_f = self._begun_f, None
        if f is None and begun is not None and begun[0] is ws and self.temporal + ws.floor == 0 \
                and np.array_equal(begun[1], s) and np.array_equal(begun[2], self.linear):
            f = begun[3]  # the begun solve's own: its B'M^2 s not formed twice (a 1006 x 216 product at 72 x 1000)
        if ws.marker_space is False:
            return None, f if f is not None else self._linear_term(
                ws, self._BtD @ (s if ws.rows is None else np.where(ws.rows, s, 0.0)))
        if f is None:
            f = self._linear_term(ws, self._marker_data(ws, s))
        x = ws.marker_space.solve(f, self._prev, self.frame_passes, self._near(ws))
        self.iterations = ws.marker_space.iterations
        if x is not None:
            stops = [s for s in getattr(_STOPS, "last", ()) if s[3]() is not ws.marker_space]
            # (weak: a finished take's solvers are not kept alive by a worker thread's record)
            _STOPS.last = [(weakref.ref(self.basis), self._row_w, ws.rows, weakref.ref(ws.marker_space))] + \
                stops[:_STOPS_KEPT - 1]
        return x, f

    def _near(self, ws: _Workspace) -> tuple | None:
        """Where this solve starts at the very point where one of this thread's last marker-space solves stopped, on
        the same basis and marker weights and a superset of this pattern's rows (kalman's held-out trial warm from
        that frame's fit, at another prior strength and without a fold's markers; kalman's fit at a new strength warm
        from the last frame's): that solver and our rows' indices in its rows, so that a refactor may take the peer's
        kept S instead of forming ours over a stale free set (solvers.marker_space_qp ``_from_peer``; issue 39)."""
        mine = self._all_rows if ws.rows is None else ws.rows
        start = self._prev
        for basis, row_w, rows, peer in getattr(_STOPS, "last", ()):
            peer = peer()
            carry = None if peer is None else peer._carry
            if (basis() is not self.basis or peer is ws.marker_space or carry is None or carry[0][0] != start[0]
                    or not np.array_equal(carry[0], start) or not np.array_equal(row_w, self._row_w)):
                continue
            theirs = self._all_rows if rows is None else rows
            if not np.any(mine & ~theirs):
                return peer, np.flatnonzero(mine[theirs])
        return None

    def begin(self, target: np.ndarray, valid: np.ndarray, passes: int, now: int | None = None) -> bool:
        """The first ``passes`` passes of the marker-space solve that ``step(target, valid)`` would run next (from
        the start ``warm`` set), now; that step continues from them. False where the step would not take that
        path. A caller so spreads one solve over two frames (kalman's held-out trial at 72 x 1000, issue 39).
        ``now``: only this many of them now, and the next one's factor (MarkerSpaceQP.begin); the step runs the
        rest."""
        s = np.asarray(target, dtype=np.float64).reshape(-1)
        seen = np.asarray(valid, dtype=bool).reshape(-1)
        if (not self.marker_space or s.shape[0] != 3 * self.n or seen.shape[0] != self.n
                or not math.isfinite(np.add.reduce(s))
                or np.count_nonzero((self._prev > self.lower) & (self._prev < self.upper)) < 3 * self.n):
            return False
        ws = self._frame_workspace(seen.tobytes(), seen)
        if ws is None:
            return False
        self._build_marker_space(ws)
        if ws.marker_space is False:
            return False
        f = self._linear_term(ws, self._marker_data(ws, s))
        ws.marker_space.begin(f, self._prev, passes, self.frame_passes, self._near(ws), now)
        self._begun_f = (ws, s.copy(), np.array(self.linear, dtype=np.float64), f)
        return True

    def _marker_data(self, ws: _Workspace, s: np.ndarray) -> np.ndarray:
        """B'M^2 s on the pattern's rows from its marker-space solver's J (MarkerSpaceQP.data_term: the matrix its
        passes read next), not from B'M^2: at 72 x 1000 a 1.7 MB read fewer a solve (issue 39; equal to rounding)."""
        rows = self._all_rows if ws.rows is None else ws.rows
        return ws.marker_space.data_term((s * np.sqrt(self._row_w))[rows])

    def _build_marker_space(self, ws: _Workspace) -> None:
        if ws.marker_space is None:
            rows = self._all_rows if ws.rows is None else ws.rows
            J = self.basis[rows] * np.sqrt(self._row_w[rows])[:, None]
            # a pattern with markers hidden: its S from the nearest pattern built on more rows (the all-seen one; a
            # held-out trial's fold pattern), as MarkerSpaceQP ``whole``
            whole = None
            for other in self._models.values() if ws.rows is not None else ():
                theirs = self._all_rows if other.rows is None else other.rows
                if (isinstance(other.marker_space, MarkerSpaceQP) and other.floor == ws.floor
                        and (whole is None or other.marker_space.r < whole[0].r) and not np.any(rows & ~theirs)):
                    whole = (other.marker_space, theirs)
            whole = None if whole is None else (whole[0], np.flatnonzero(rows[whole[1]]))
            key = rows.tobytes()
            try:
                ws.marker_space = MarkerSpaceQP(J, np.diagonal(self._const) + ws.floor, self.lower, self.upper,
                                                whole=whole, same=self._marker_J.get(key))
                self._marker_J.setdefault(key, ws.marker_space)
            except (np.linalg.LinAlgError, ValueError) as exc:  # e.g. too few markers seen to fix the pose
                log.debug("marker-space QP not built: %s", exc)
                ws.marker_space = False

    def prepare_marker_space(self) -> None:
        """Build the marker-space solver of every pattern seen so far now, where this QP may take that path: the
        expensive preparation (an r x r product over every column, ~9 ms at 72 x 1000) before the stream, not on
        the frame that first needs it."""
        if self.marker_space:
            for ws in self._models.values():
                self._build_marker_space(ws)

    def _fallback(self, ws: _Workspace, f: np.ndarray) -> np.ndarray:
        x = np.linalg.lstsq(ws.H, -f, rcond=None)[0]
        if not np.all(np.isfinite(x)):
            return self._prev.copy()
        return np.minimum(np.maximum(x, self.lower), self.upper)
