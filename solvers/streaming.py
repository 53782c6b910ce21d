"""Streaming movement matching: a sliding window with prefactored matrices (Seol et al. 2012 §4-5, §7.1).

At frame t the unknowns are the K frames t-K+1 .. t; the left boundary is frame t-K, already
published (weights fixed, Seol's boundary condition); the right end is free (no future yet).
The published output is frame t-L (lookahead L < K); frames after it stay provisional and are
re-solved by the next windows. Every matrix is constant, and in the decoupled coordinates of
:mod:`solvers.blocks` each mode is one K x K tridiagonal system, so the published frame is a
fixed linear function of the projected data in the window:

    y_out[k] = sum_s F[k, s] q_s[k] + sum_s Fb[k, s] qb_s[k] + a[k] (U^T G w_left)[k] + c[k]

F, Fb, a, c are computed once (LDL^T solves for the needed rows of the K x K inverses; the known
boundary row moves to the right-hand side as in Seol's Appendix, R = DS^T - [D3; D4] W2^T B^T).
Back in weights (w = U y, the decoupling of :mod:`solvers.blocks`) the published frame is

    w_out = U x + U diag(a) U^T G w_left + U c,   x = the window sum above,

so the boundary and prior terms fold into one constant m x (d + m + 1) matrix [U | U diag(a) U^T G
| U c] applied to the stacked vector [x; w_left; 1] (d = m, or 2m with per-marker weights). A frame
costs one (d x 3n) product to project the new markers, one (K+1) x d weighted sum and that one
product back to weights: no factorisation, no allocation but the returned array. The newest
window row (the constant-velocity prediction for missing markers) is only formed on frames that
need it.

Drift: with a free right end nothing but the prior and the position term (beta) ties the weights
to absolute marker positions, so ``beta > 0`` (default 0.05) is what keeps a long stream from
wandering; the published left boundary carries the history. Rig limits: projection (clip) of
the published frame, which then becomes the next windows' boundary, so later frames move on from
the limited pose. Missing markers: imputed as the rig's fit at the constant-velocity prediction
of the newest frame plus the marker's offset from the fit when it was last seen (no NaN, no
change to the matrices).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dpttrf, dpttrs

from solvers.blocks import MovementBlocks
from solvers.prior import PCAPrior


class StreamingMovement:
    """Per-frame ``step(target, valid)`` with K-frame window and lookahead L; ``solve`` runs a take."""

    def __init__(self, basis: np.ndarray, lower: np.ndarray | None = None, upper: np.ndarray | None = None, *,
                 window: int = 24, lookahead: int = 0, alpha: float = 0.0, prior: PCAPrior | None = None,
                 beta: float = 0.05, marker_weights: np.ndarray | None = None, ridge: float = 0.0,
                 limits: str = "clip", blocks: MovementBlocks | None = None) -> None:
        K, L = int(window), int(lookahead)
        if K < 1 or not 0 <= L < K:
            raise ValueError(f"need window >= 1 and 0 <= lookahead < window (got window={K}, lookahead={L})")
        if limits not in ("clip", "none"):
            raise ValueError(f"limits must be 'clip' or 'none', got {limits!r}")
        b = blocks or MovementBlocks(basis, alpha=alpha, prior=prior, beta=beta, marker_weights=marker_weights,
                                     ridge=ridge)
        self.blocks = b
        m = b.n_shapes
        self.window, self.lookahead, self.limits = K, L, limits
        self.lower = np.full(m, -np.inf) if lower is None else np.asarray(lower, dtype=np.float64)
        self.upper = np.full(m, np.inf) if upper is None else np.asarray(upper, dtype=np.float64)
        self._clip = limits == "clip" and (np.isfinite(self.lower).any() or np.isfinite(self.upper).any())
        rw = b.row_weights
        # with one weight for every marker the position data is a multiple of the movement data
        self._fold = b.Qb is None or bool(np.all(rw == rw[0]))
        self._has_b = not self._fold
        self.P = np.ascontiguousarray(np.vstack([b.Qm, b.Qb]) if self._has_b else b.Qm)  # (2m or m) x 3n
        self._rows = self._window_rows(K)  # K x (K+1) x 2m coefficients for every window row
        jo = K - 1 - L
        self._U, self._UG, self._BU = b.U, b.UG, b.BU
        self._m, self._S, self._R = m, K + 1, K + 3
        self._F0 = np.ascontiguousarray(self._rows[jo])  # (K+1) x d coefficients of the published row
        self._F01 = np.ascontiguousarray(self._rows[[jo, K - 1]])  # with the newest row (imputation)
        self._a01, self._c01 = self._a[[jo, K - 1]], self._c[[jo, K - 1]]
        # The published frame in weights is one product of a constant matrix with the stacked vector
        # v = [window sum (d); w_left (m); 1]:  w = U x + U diag(a) U^T G w_left + U c  (d = 2m sums the
        # movement and position halves through U twice). One m x (d + m + 1) product per frame.
        d = self.P.shape[0]
        self._UM = np.ascontiguousarray(np.hstack([b.U] * (d // m) + [b.U @ (self._a[jo][:, None] * b.UG),
                                                                      (b.U @ self._c[jo])[:, None]]))
        self._v = np.ones(d + m + 1)
        self._v_sum, self._v_left = self._v[:d], self._v[d:d + m]  # views filled per frame
        self._tmp, self._ones = np.empty((K + 1, d)), np.ones(K + 1)
        self.reset()

    # ------------------------------------------------------------------------------ preparation
    def _window_rows(self, K: int) -> np.ndarray:
        """Coefficients turning the window's projected data into each window frame's modal weights.

        Window matrix per mode: g_k L_K + (1 - g_k) I, with L_K the path Laplacian whose first
        frame is tied to the fixed left boundary and whose last frame has no successor.
        """
        g = self.blocks.g
        m = len(g)
        deg = np.full(K, 2.0)
        deg[-1] = 1.0
        d = (g[:, None] * deg[None, :] + (1.0 - g)[:, None]).ravel()
        e = np.zeros((m, K))
        e[:, :-1] = -g[:, None]
        d, e, info = dpttrf(d, e.ravel()[:-1])
        if info != 0:
            raise ValueError("streaming window is singular: set beta, alpha (with a prior) or ridge > 0")
        # rows of the per-mode inverse: the inverse is symmetric, so row j = solution for e_j
        rhs = np.zeros((m * K, K))
        for j in range(K):
            rhs[np.arange(m) * K + j, j] = 1.0
        inv, _ = dpttrs(d, e, rhs)
        Ainv = inv.reshape(m, K, K).transpose(2, 0, 1)  # [row j, mode k, tau]
        # r_tau = dq_tau - dq_{tau+1}, dq_tau = q[tau+1] - q[tau] over the history s = 0..K (s=0: boundary)
        Dm = np.zeros((K, K + 1))
        for tau in range(K):
            Dm[tau, tau + 1] += 1.0
            Dm[tau, tau] -= 1.0
            if tau + 1 < K:
                Dm[tau, tau + 2] -= 1.0
                Dm[tau, tau + 1] += 1.0
        Fq = np.einsum("jkt,ts->jsk", Ainv, Dm)  # K x (K+1) x m
        parts = [Fq]
        if self.blocks.Qb is not None:
            Fb = np.zeros_like(Fq)
            Fb[:, 1:, :] = Ainv.transpose(0, 2, 1)
            if self._fold:  # qb = beta M^2 q: one set of coefficients
                parts = [Fq + self.blocks.beta * self.blocks.row_weights[0] * Fb]
            else:
                parts.append(Fb)
        self._a = Ainv[:, :, 0]  # K x m: weight of the boundary term U^T G w_left (enters r_0)
        self._c = Ainv.sum(2) * self.blocks.const[None, :]  # K x m: the prior constant in every r_tau
        return np.concatenate(parts, axis=2)

    # ------------------------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the stream: the next frame starts a new one."""
        self._t = 0
        self._started = False

    def _start(self, s: np.ndarray, valid: np.ndarray) -> None:
        """Initial state: the first frame's per-frame fit, as if the face had held it for a while."""
        b = self.blocks
        rows = np.repeat(valid, 3)
        m = b.n_shapes
        if rows.any():  # per-frame fit of the visible markers with the same prior/beta/ridge terms
            Bv, rw = b.basis[rows], 1.0 + b.beta * b.row_weights[rows]
            Kv = b.K - b.beta * (b.basis.T @ (b.row_weights[:, None] * b.basis))
            A = Bv.T @ (rw[:, None] * Bv) + Kv + 1e-9 * np.trace(b.G) / m * np.eye(m)
            w0 = np.linalg.solve(A, Bv.T @ (rw * s[rows]) + b.const_weights)
        else:
            w0 = np.zeros(m)
        if self._clip:
            w0 = np.clip(w0, self.lower, self.upper)
        s0 = np.where(rows, s, b.basis @ w0)
        R = self._R
        # rings over frames mod R = K + 3 (frame t's window and the two before it, which the imputation
        # may need after frame t was written): the projected data, stored twice so that every window
        # is one contiguous slice, and the published weights (a boundary K - L frames later)
        self._z = np.tile(self.P @ s0, (2 * R, 1))
        self._w = np.tile(w0, (R, 1))
        y0 = b.U.T @ ((b.G + b.K) @ w0)
        self._ynew, self._ynew_frame = np.tile(y0, (3, 1)), [-3, -2, -1]  # by frame mod 3
        self._s_last = s0.copy()
        self._gap = np.zeros(len(valid), dtype=bool)
        self._gapping = False
        self._off = np.zeros(3 * len(valid))  # per coordinate row
        self._started = True

    def _window(self, f: int) -> np.ndarray:
        """Projected data of frame f's window, frames f - K .. f (the first is the boundary)."""
        i = (f - self.window) % self._R
        return self._z[i:i + self._S]

    def _solve_rows(self, f: int, rows: np.ndarray) -> np.ndarray:
        """Modal weights of the given rows of frame f's window (len(rows) x m), from the rings."""
        acc = np.einsum("rsj,sj->rj", self._rows[rows], self._window(f))
        m = self._m
        y = acc[:, :m] + acc[:, m:] if self._has_b else acc
        return y + self._a[rows] * (self._UG @ self._w[(f - self.window) % self._R]) + self._c[rows]

    def _newest(self, f: int) -> np.ndarray:
        """Modal weights of frame f as its own window's newest (free) frame. Only the imputation uses
        them (frames t - 1 and t - 2): imputed frames keep theirs, others are recomputed on demand."""
        k = f % 3
        if self._ynew_frame[k] != f:
            self._keep_newest(f, self._solve_rows(f, np.array([self.window - 1]))[0])
        return self._ynew[k]

    def _keep_newest(self, f: int, y: np.ndarray) -> None:
        self._ynew[f % 3] = y
        self._ynew_frame[f % 3] = f

    def _impute(self, s: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Missing markers from the rig's fit at the predicted newest frame plus their last offset."""
        missing = ~valid
        y1, y2 = self._newest(self._t - 1), self._newest(self._t - 2)
        opened = missing & ~self._gap
        if np.count_nonzero(opened):  # gone this frame: remember the offset from the fit when last seen
            np.copyto(self._off, self._s_last - self._BU @ y1, where=np.repeat(opened, 3))
        self._gap = missing
        self._gapping = True
        return np.where(np.repeat(missing, 3), self._BU @ (2.0 * y1 - y2) + self._off, s)

    def _clean(self, s: np.ndarray, valid: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """A NaN/inf coordinate makes its marker missing, never a NaN weight."""
        valid = np.ones(len(s) // 3, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
        if not math.isfinite(s.sum()):
            valid = valid & np.isfinite(s).reshape(-1, 3).all(1)
            s = np.where(np.repeat(valid, 3), s, 0.0)
        return s, valid

    # --------------------------------------------------------------------------------- per frame
    def step(self, target: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Weights of frame t - lookahead, given frame t's marker displacements (n x 3, mm).

        Per frame (Seol §4 with the window's factorisation done at preparation): project the new
        frame, take the published row's weighted sum over the window, and one product back to
        weights. The common case (all markers valid and finite) runs on preallocated buffers;
        otherwise missing markers are imputed first.
        """
        s = np.asarray(target, dtype=np.float64).reshape(-1)
        if not self._started:
            self._start(*self._clean(s, valid))
        t, R, K = self._t, self._R, self.window
        z = self._z[t % R]
        complete = valid is None or np.count_nonzero(valid) == len(valid)
        if complete:
            np.dot(self.P, s, out=z)  # q_t = U^T B^T s_t
            # a NaN/inf anywhere in s makes every component of z non-finite (0 * nan = nan): z[0] tells
            complete = math.isfinite(z[0])
        if not complete:
            s, valid = self._clean(s, valid)
            complete = np.count_nonzero(valid) == len(valid)  # finite data, overflowing projection
            if not complete:
                s = self._impute(s, valid)
                np.dot(self.P, s, out=z)
        if complete and self._gapping:
            self._gap[:] = False
            self._gapping = False
        self._z[t % R + R] = z
        i = (t - K) % R
        H, w = self._z[i:i + self._S], self._w[(t - self.lookahead) % R]
        if complete:  # x = sum_s F0[s] * H[s]: an elementwise product, then a BLAS sum over the window
            np.dot(self._ones, np.multiply(self._F0, H, out=self._tmp), out=self._v_sum)
            self._v_left[:] = self._w[i]  # the boundary: weights published K - L frames ago
            np.dot(self._UM, self._v, out=w)
        else:  # imputed: the newest row too, as the next frame's imputation starts from it
            y = np.einsum("rsj,sj->rj", self._F01, H)
            if self._has_b:
                y = y[:, :self._m] + y[:, self._m:]
            y += self._a01 * (self._UG @ self._w[i])
            y += self._c01
            self._keep_newest(t, y[1])
            np.dot(self._U, y[0], out=w)
        if self._clip:  # projection onto the rig's limits; the clipped frame is the later boundary
            np.maximum(w, self.lower, out=w)
            np.minimum(w, self.upper, out=w)
        np.copyto(self._s_last, s)
        self._t = t + 1
        return w.copy()

    def pending(self) -> np.ndarray:
        """The provisional frames after the last published one (L x m), from the latest window."""
        L, K = self.lookahead, self.window
        if not self._started or L == 0:
            return np.zeros((0, self.blocks.n_shapes))
        W = self._solve_rows(self._t - 1, np.arange(K - L, K)) @ self._U.T
        return np.clip(W, self.lower, self.upper) if self._clip else W

    def solve(self, targets: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """A whole take through the stream, realigned: frame i of the result is frame i of the take."""
        T = len(targets)
        X = np.asarray(targets, dtype=np.float64).reshape(T, -1)
        V = np.ones((T, X.shape[1] // 3), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
        self.reset()
        out = np.array([self.step(X[i], V[i]) for i in range(T)]).reshape(T, -1)
        L = min(self.lookahead, T)
        W = np.vstack([out[L:], self.pending()[self.lookahead - L:]])
        self.reset()
        return W
