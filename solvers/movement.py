"""Offline movement matching and spacetime editing (Seol et al. 2012 §4-7 and appendix).

Solve a whole take at once for the weights W (T x m) minimising

    sum_t |B(w_t - w_{t-1}) - (s_t - s_{t-1})|^2                 movement (§4, Eq. 2)
      + alpha sum_t prior(w_t)                                    PCA prior (§5, Eq. 4)
      + beta  sum_t |M(B w_t - s_t)|^2                            Sobolev position term (§7.1)
      + ridge sum_t |w_t|^2                                       (numerical safety, default 0)

with known frames as boundary conditions (neutral at the take's start/end, or any fixed
frames). The normal equations are block-tridiagonal with constant blocks; they are decoupled
(see :mod:`solvers.blocks`) into m independent SPD tridiagonal systems, stacked into one and
factored by LAPACK ``pttrf`` (LDL^T, O(mT)). The cost is dominated by projecting the data,
O(T n m): milliseconds for 1000 frames.

Missing markers break the constant blocks (the rows of G = B^T B would vary per frame).
Default ``missing="fill"``: fill each gap with the rig's own fit plus the marker's offset from
the fit, interpolated linearly between the observed frames around the gap, and iterate
(solve, refill) a few times; every iteration reuses the factorisation. At the fixed point a
missing marker moves like the rig predicts and its total movement across the gap matches what
was observed either side. ``missing="exact"`` instead drops the rows of missing markers from
every term (the literal masked objective) and solves the varying block-tridiagonal system
with a block Thomas sweep (O(T m^3), see :mod:`solvers.masked`).

Spacetime editing (§6): an edit sets some weights at frame k (the others keep their current
value, so the whole pose at k becomes a boundary condition); with a propagation range [a, b]
frames a and b keep their current values and only frames strictly inside are re-solved
against the source movement. Several edits compose: their ranges merge, every edit frame is a
boundary.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg.lapack import dpttrs

from solvers.blocks import MovementBlocks, factor_modes
from solvers.prior import PCAPrior

Boundary = str | np.ndarray | None  # "neutral", "free", "fit", or an (m,) weight vector


@dataclass(frozen=True)
class Edit:
    """Set ``weights`` (shape index -> value, or a full (m,) vector) at ``frame``; re-solve only
    inside ``range`` = (a, b) (both ends keep their current values; None: the whole take)."""

    frame: int
    weights: Mapping[int, float] | np.ndarray
    range: tuple[int, int] | None = None


def edit_region(edits: Sequence[Edit], T: int) -> np.ndarray:
    """Frames a set of edits re-solves (Seol §6): inside each range, ends and edited frames excluded."""
    region = np.zeros(T, dtype=bool)
    for e in edits:
        k = int(e.frame)
        a, b = (0, T - 1) if e.range is None else (int(e.range[0]), int(e.range[1]))
        if not (0 <= a <= k <= b <= T - 1):
            raise ValueError(f"edit at frame {k}: range [{a}, {b}] must satisfy 0 <= a <= k <= b <= {T - 1}")
        region[a + 1:b] = True
    region[[int(e.frame) for e in edits]] = False
    return region


class GapPlan:
    """Where markers are missing and which observed frames bracket each gap (computed once per take)."""

    def __init__(self, valid: np.ndarray) -> None:
        valid = np.asarray(valid, dtype=bool)
        self.shape = valid.shape
        self.t, self.i = np.nonzero(~valid)
        E = len(self.t)
        self.a = np.zeros(E, dtype=np.intp)  # observed frame before (or the first observed)
        self.b = np.zeros(E, dtype=np.intp)  # observed frame after (or the last observed)
        self.lam = np.zeros(E)
        self.never = np.zeros(E, dtype=bool)  # marker never observed: the fit alone
        for i in np.unique(self.i):
            sel = np.flatnonzero(self.i == i)
            seen = np.flatnonzero(valid[:, i])
            if len(seen) == 0:
                self.never[sel] = True
                continue
            t = self.t[sel]
            right = np.clip(np.searchsorted(seen, t), 0, len(seen) - 1)
            left = np.clip(np.searchsorted(seen, t) - 1, 0, len(seen) - 1)
            ta, tb = seen[left], seen[right]
            span = np.where(tb > ta, tb - ta, 1)
            self.a[sel], self.b[sel] = ta, tb
            self.lam[sel] = np.where(tb > ta, (t - ta) / span, 0.0)
        self.frames = np.unique(self.t)  # frames whose targets change when refilled

    @property
    def empty(self) -> bool:
        return len(self.t) == 0

    def fill(self, targets: np.ndarray, weights: np.ndarray | None = None, basis: np.ndarray | None = None
             ) -> np.ndarray:
        """Targets with each missing marker = fit + offset from the fit interpolated across its gap."""
        S = np.asarray(targets, dtype=np.float64)
        if self.empty:
            return S
        out = S.copy()
        if weights is None:
            def fit(t, i):
                return np.zeros((len(t), 3))
        else:
            Bn = basis.reshape(S.shape[1], 3, -1)

            def fit(t, i):
                return np.einsum("ecm,em->ec", Bn[i], weights[t])
        i = self.i
        lam = self.lam[:, None]
        off = (1.0 - lam) * (S[self.a, i] - fit(self.a, i)) + lam * (S[self.b, i] - fit(self.b, i))
        off[self.never] = 0.0
        out[self.t, i] = fit(self.t, i) + off
        return out


def fill_gaps(targets: np.ndarray, valid: np.ndarray, weights: np.ndarray | None = None,
              basis: np.ndarray | None = None) -> np.ndarray:
    """Missing markers replaced by the rig's fit (``weights`` through ``basis``) plus the marker's
    offset from the fit, the offset interpolated linearly in time between observed frames (held
    at the take's ends; 0 for a marker never seen). Without weights: linear interpolation."""
    return GapPlan(valid).fill(targets, weights, basis)


class MovementMatching:
    """Offline movement matching over whole takes, spacetime edits, and (through
    :class:`solvers.streaming.StreamingMovement`) a per-frame ``step`` for live use.

    Takes plain arrays: ``basis`` (3n x m), ``lower``/``upper`` weight limits (m,). ``limits``:
    "none" (Seol: the prior keeps weights plausible), "clip" (project the result onto the
    limits afterwards) or "bound" (minimise the objective *subject to* the limits, Seol §4 Fig. 3
    and §7 Fig. 11: :class:`solvers.bounded.BoundedMovement`, ADMM warm-started from the clipped
    unbounded solve; ``bound_options`` are passed to it, e.g. ``{"tol": 1e-6}``).
    """

    def __init__(self, basis: np.ndarray, lower: np.ndarray | None = None, upper: np.ndarray | None = None, *,
                 alpha: float = 0.0, prior: PCAPrior | None = None, beta: float = 0.0,
                 marker_weights: np.ndarray | None = None, ridge: float = 0.0,
                 start: Boundary = "neutral", end: Boundary = "neutral", missing: str = "fill",
                 fill_iterations: int = 3, limits: str = "none", window: int = 24, lookahead: int = 0,
                 blocks: MovementBlocks | None = None, bound_options: Mapping | None = None) -> None:
        self.blocks = blocks or MovementBlocks(basis, alpha=alpha, prior=prior, beta=beta,
                                               marker_weights=marker_weights, ridge=ridge)
        m = self.blocks.n_shapes
        self.lower = np.full(m, -np.inf) if lower is None else np.asarray(lower, dtype=np.float64)
        self.upper = np.full(m, np.inf) if upper is None else np.asarray(upper, dtype=np.float64)
        if missing not in ("fill", "exact"):
            raise ValueError(f"missing must be 'fill' or 'exact', got {missing!r}")
        if limits not in ("none", "clip", "bound"):
            raise ValueError(f"limits must be 'none', 'clip' or 'bound', got {limits!r}")
        self.bound_options = dict(bound_options or {})
        self._bounder = None  # BoundedMovement, prepared on first use
        self.bounded_info = None  # how the last bounded solve ended
        self.start, self.end, self.missing, self.limits = start, end, missing, limits
        self.fill_iterations = int(fill_iterations)
        self.window, self.lookahead = int(window), int(lookahead)
        self._q: np.ndarray | None = None  # projected data of the last solved take (for edits)
        self._qb: np.ndarray | None = None
        self._targets: np.ndarray | None = None
        self._stream = None

    # ----------------------------------------------------------------------------------- offline
    def boundary_frames(self, targets: np.ndarray, valid: np.ndarray,
                        fixed: Mapping[int, np.ndarray] | None = None) -> dict[int, np.ndarray]:
        """The fixed frames: start/end conditions plus ``fixed`` (negative frames count from the end)."""
        T, m = len(targets), self.blocks.n_shapes
        out: dict[int, np.ndarray] = {}
        for frame, spec in ((0, self.start), (T - 1, self.end)):
            w = self._boundary_value(spec, targets[frame], valid[frame])
            if w is not None:
                out[frame] = w
        for frame, w in (fixed or {}).items():
            f = int(frame) + (T if int(frame) < 0 else 0)
            if not 0 <= f < T:
                raise ValueError(f"fixed frame {frame} outside the take (0..{T - 1})")
            w = np.asarray(w, dtype=np.float64)
            if w.shape != (m,):
                raise ValueError(f"fixed frame {frame}: expected {m} weights, got shape {w.shape}")
            out[f] = w
        return out

    def _boundary_value(self, spec: Boundary, target: np.ndarray, valid: np.ndarray) -> np.ndarray | None:
        m = self.blocks.n_shapes
        if spec is None or (isinstance(spec, str) and spec == "free"):
            return None
        if isinstance(spec, str):
            if spec == "neutral":
                return np.zeros(m)
            if spec == "fit":  # per-frame least-squares fit of the visible markers (Seol §4)
                rows = np.repeat(valid, 3)
                B = self.blocks.basis[rows]
                return np.linalg.lstsq(B, target.reshape(-1)[rows], rcond=None)[0] if rows.any() else np.zeros(m)
            raise ValueError(f"unknown boundary {spec!r} (use 'neutral', 'free', 'fit' or weights)")
        w = np.asarray(spec, dtype=np.float64)
        if w.shape != (m,):
            raise ValueError(f"boundary weights must have shape ({m},), got {w.shape}")
        return w

    def solve(self, targets: np.ndarray, valid: np.ndarray | None = None,
              fixed: Mapping[int, np.ndarray] | None = None, linear: np.ndarray | None = None) -> np.ndarray:
        """Weights (T x m) for stabilised marker displacements ``targets`` (T x n x 3, mm).

        ``linear`` (m,) or (T, m) adds sum_t linear_t . w_t to the objective (e.g. an L1 term on
        non-negative weights); fixed frames ignore it.
        """
        S = np.asarray(targets, dtype=np.float64)
        T = len(S)
        S = S.reshape(T, -1, 3)
        valid = np.ones(S.shape[:2], dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
        m = self.blocks.n_shapes
        if T == 0:
            return np.zeros((0, m))
        bounds = self.boundary_frames(S, valid, fixed)
        lin = None if linear is None else np.broadcast_to(np.asarray(linear, dtype=np.float64), (T, m))
        W = np.zeros((T, m))
        isfree = np.ones(T, dtype=bool)
        for f, w in bounds.items():
            W[f] = w
            isfree[f] = False
        free = np.flatnonzero(isfree)
        B = self.blocks.basis
        if self.missing == "exact" and not valid.all():
            from solvers.masked import solve_masked

            if lin is not None:
                raise ValueError("a linear term needs missing='fill' (the exact masked solve has none)")
            W = solve_masked(self.blocks, S, valid, W, isfree)
            filled = fill_gaps(S, valid, W, B)
            q, qb = self.blocks.project(filled)
        else:
            plan = GapPlan(valid)
            filled = plan.fill(S)
            q, qb = self.blocks.project(filled)
            factor = self._factor(free, T)
            W = self._solve_factored(factor, None, free, isfree, W, q, qb, lin)
            rows = plan.frames
            for _ in range(0 if plan.empty else self.fill_iterations):
                filled = plan.fill(S, W, B)
                q[rows] = filled[rows].reshape(len(rows), -1) @ self.blocks.Qm.T
                if qb is not None:
                    qb[rows] = filled[rows].reshape(len(rows), -1) @ self.blocks.Qb.T
                W = self._solve_factored(factor, None, free, isfree, W, q, qb, lin)
        if self.limits == "bound":  # gaps stay filled from the unbounded fit's iterations
            W = self._bounded(q, qb, free, isfree, W, lin)
        self._targets = filled
        self._q, self._qb = q, qb
        return self._apply_limits(W, free)

    def _bounded(self, q: np.ndarray, qb: np.ndarray | None, free: np.ndarray, isfree: np.ndarray, W: np.ndarray,
                 linear: np.ndarray | None = None) -> np.ndarray:
        """Re-solve the free frames inside the limits, warm-started from W (the unbounded solve)."""
        if len(free) == 0:
            return W
        if self._bounder is None:
            from solvers.bounded import BoundedMovement

            self._bounder = BoundedMovement(self.blocks, self.lower, self.upper, **self.bound_options)
        r = self._rhs(q, qb, free, isfree, W, linear) @ self.blocks.NU.T  # weight-space right-hand side
        W = W.copy()
        W[free] = self._bounder.solve(r, free, len(q), W[free])
        self.bounded_info = self._bounder.info
        return W

    def _apply_limits(self, W: np.ndarray, frames: np.ndarray) -> np.ndarray:
        if self.limits == "clip" and len(frames):
            W[frames] = np.clip(W[frames], self.lower, self.upper)
        return W

    def _factor(self, free: np.ndarray, T: int):
        """LDL^T of the m stacked tridiagonal systems (g_k L_ff + (1 - g_k) I) over the free frames."""
        return factor_modes(self.blocks.g, free, T)

    def _solve_factored(self, factor, targets: np.ndarray, free: np.ndarray, isfree: np.ndarray,
                        W: np.ndarray, q: np.ndarray | None = None, qb: np.ndarray | None = None,
                        linear: np.ndarray | None = None) -> np.ndarray:
        if factor is None:
            return W
        if q is None:
            q, qb = self.blocks.project(targets)
        r = self._rhs(q, qb, free, isfree, W, linear)
        y, info = dpttrs(*factor, r.T.reshape(-1, 1))
        W = W.copy()
        W[free] = self.blocks.to_weights(y.reshape(len(self.blocks.g), -1).T)
        return W

    def _rhs(self, q: np.ndarray, qb: np.ndarray | None, free: np.ndarray, isfree: np.ndarray,
             W: np.ndarray, linear: np.ndarray | None = None) -> np.ndarray:
        """Projected right-hand side U^T r for the free frames (appendix: known rows moved right);
        a linear term mu.w in the objective moves r by -mu/2."""
        T, m = q.shape
        dq = np.zeros((T + 1, m))
        dq[1:T] = q[1:] - q[:-1]  # dq[t] = q_t - q_{t-1}; no pair before frame 0 or after T-1
        r = dq[free] - dq[free + 1] + self.blocks.const
        if qb is not None:
            r += qb[free]
        for nb in (free - 1, free + 1):
            ok = (nb >= 0) & (nb < T)
            ok[ok] = ~isfree[nb[ok]]
            if ok.any():
                r[ok] += W[nb[ok]] @ self.blocks.UG.T
        if linear is not None:
            r -= 0.5 * linear[free] @ self.blocks.U
        return r

    # ----------------------------------------------------------------------------------- editing
    def edit(self, weights: np.ndarray, edits: Sequence[Edit], targets: np.ndarray | None = None,
             valid: np.ndarray | None = None, linear: np.ndarray | None = None) -> np.ndarray:
        """Apply spacetime edits (§6) to ``weights`` (T x m); frames outside every range are untouched.

        The source movement is ``targets`` (T x n x 3) or, when None, the take of the last
        :meth:`solve`; ``linear`` is the same objective term as in :meth:`solve`, so a range is
        re-solved under the objective that produced the weights around it.
        """
        W = np.array(weights, dtype=np.float64)
        T, m = W.shape
        if targets is None and (self._q is None or len(self._q) != T):
            raise ValueError("edit needs the source targets (or a preceding solve of a take of the same length)")
        region = edit_region(edits, T)
        poses: dict[int, np.ndarray] = {}
        for e in edits:
            k = int(e.frame)
            pose = poses.get(k, W[k]).copy()
            if isinstance(e.weights, Mapping):
                for j, val in e.weights.items():
                    if not 0 <= int(j) < m:
                        raise ValueError(f"edit at frame {k}: shape index {j} outside 0..{m - 1}")
                    pose[int(j)] = float(val)
            else:
                pose = np.asarray(e.weights, dtype=np.float64).copy()
                if pose.shape != (m,):
                    raise ValueError(f"edit at frame {k}: expected {m} weights, got shape {pose.shape}")
            poses[k] = pose
        for k, pose in poses.items():
            W[k] = pose
        free = np.flatnonzero(region)
        if len(free) == 0:
            return W
        lo, hi = free[0] - 1, free[-1] + 1  # both fixed: a range end or an edit frame
        sub = slice(lo, hi + 1)
        if targets is not None:  # project only the frames being re-solved
            S = np.asarray(targets, dtype=np.float64).reshape(T, -1, 3)
            v = np.ones(S.shape[:2], dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
            if not v.all():
                S = fill_gaps(S, v, weights, self.blocks.basis)
            q, qb = self.blocks.project(S[sub])
        else:
            q, qb = self._q[sub], None if self._qb is None else self._qb[sub]
        isfree = region[sub]
        f_local = free - lo
        factor = self._factor(f_local, hi - lo + 1)
        lin = None if linear is None else np.broadcast_to(np.asarray(linear, dtype=np.float64), (T, m))[sub]
        Wsub = self._solve_factored(factor, None, f_local, isfree, W[sub], q, qb, lin)
        if self.limits == "bound":
            Wsub = self._bounded(q, qb, f_local, isfree, Wsub, lin)
        W[sub] = Wsub
        return self._apply_limits(W, free)

    # ----------------------------------------------------------------------------------- live use
    def _streaming(self):
        if self._stream is None:
            from solvers.streaming import StreamingMovement

            self._stream = StreamingMovement(self.blocks.basis, self.lower, self.upper, window=self.window,
                                             lookahead=self.lookahead, blocks=self.blocks,
                                             limits="clip" if np.isfinite(self.lower).all() else "none")
        return self._stream

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Live use: the sliding-window solver with the same blocks (see :mod:`solvers.streaming`)."""
        return self._streaming().step(target, valid)

    def reset(self) -> None:
        if self._stream is not None:
            self._stream.reset()
