"""Movement matching with the weight limits active: a box-constrained spacetime QP solved by ADMM.

Seol et al. 2012 §4 (Fig. 3) and §7 (Fig. 11) compare movement matching *with constraints
active*: least squares over derivatives spreads an unavoidable error as many small velocity
errors instead of the few large ones that per-frame clipping makes. Here the constraints are
the rig's limits, so the problem over the free frames x (N x m) is

    minimise  E(x) + sum_t mu_t . x_t     subject to  lower <= x_t <= upper,

E the movement objective of :mod:`solvers.movement` (movement + alpha prior + beta Sobolev
position + ridge, fixed/boundary frames moved to the right-hand side), mu an optional linear
term (e.g. an L1 penalty on non-negative weights). With H = L_ff (x) G + I (x) K and the
right-hand side r of the normal equations H x = r, E(x) = x^T H x - 2 r^T x + const.

ADMM (Boyd, Parikh, Chu, Peleato, Eckstein 2011, "Distributed optimization and statistical
learning via the alternating direction method of multipliers", §5.2 constrained convex QP,
§3.3 stopping, §3.4.1 varying penalty, §3.4.3 over-relaxation) splits x = z with z in the box:

    x <- argmin E(x) + mu.x + rho |x - z + u|_D^2     (H + rho I (x) D) x = r - mu/2 + rho D (z - u)
    z <- clip(a x + (1 - a) z + u, lower, upper)        (a: over-relaxation, 1.6)
    u <- u + a x + (1 - a) z_old - z

D is the diagonal of the Hessian's interior block, diag(2G + K) (a Jacobi metric: ADMM on
diagonally rescaled weights, so one rho suits every shape). The x-step has the same structure as
the unbounded solve: the generalised eigenproblem G v = g (G + K + rho D) v decouples it into m
tridiagonal systems (:mod:`solvers.blocks`), prepared once per rho; an iteration costs two
(N x m) x (m x m) products and O(N m) back-substitutions, and nothing larger than m x m is formed.
Residuals are in weight units (primal |x - z|, dual rho |z - z_old|, the gradient residual in the
Jacobi metric); rho is rebalanced from their ratio every few iterations (a refactorisation costs
one m x m eigh and one O(N m) pttrf). The result is z: inside the limits exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from scipy.linalg.lapack import dpttrs

from solvers.blocks import MovementBlocks, factor_modes


@dataclass
class BoundedInfo:
    """How the last bounded solve ended (for logs, tests and benchmarks)."""

    iterations: int
    primal_residual: float
    dual_residual: float
    converged: bool
    rho: float
    refactorisations: int
    accelerated: int = 0  # Anderson steps accepted


class BoundedMovement:
    """ADMM for movement matching inside [lower, upper] on the prepared ``blocks``.

    ``tol`` bounds both residuals in weight units; ``max_iter`` caps the iterations (the result
    is then the last feasible iterate, ``info.converged`` False).
    """

    def __init__(self, blocks: MovementBlocks, lower: np.ndarray, upper: np.ndarray, *, rho: float = 0.1,
                 tol: float = 1e-6, max_iter: int = 5000, relax: float = 1.6, adapt_every: int = 10,
                 memory: int = 5, accelerate_after: int = 30) -> None:
        self.blocks = blocks
        m = blocks.n_shapes
        self.lower = np.broadcast_to(np.asarray(lower, dtype=np.float64), (m,)).copy()
        self.upper = np.broadcast_to(np.asarray(upper, dtype=np.float64), (m,)).copy()
        if np.any(self.lower > self.upper):
            raise ValueError("bounded solve needs lower <= upper for every shape")
        d = np.diag(2.0 * blocks.G + blocks.K).copy()
        self.metric = np.maximum(d, 1e-12 * max(d.max(), 1e-300))
        self.rho0, self.tol, self.max_iter = float(rho), float(tol), int(max_iter)
        self.relax, self.adapt_every, self.memory = float(relax), int(adapt_every), int(memory)
        self.accelerate_after = int(accelerate_after)  # plain ADMM first: acceleration costs ~2x per iteration
        self.info: BoundedInfo | None = None
        self._modes: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def _modes_for(self, rho: float) -> tuple[np.ndarray, np.ndarray]:
        """(g, V) with V^T G V = diag(g), V^T (K + rho D) V = diag(1 - g): one m x m eigh per rho."""
        if rho not in self._modes:
            if len(self._modes) > 16:
                self._modes.clear()
            b = self.blocks
            g, V = scipy.linalg.eigh(b.G, b.G + b.K + rho * np.diag(self.metric))
            self._modes[rho] = (np.clip(g, 0.0, 1.0), V)
        return self._modes[rho]

    def solve(self, rhs: np.ndarray, free: np.ndarray, T: int, start: np.ndarray) -> np.ndarray:
        """Weights of the ``free`` frames (N x m) minimising E(x) - 2 rhs.x + ... inside the limits.

        ``rhs`` (N x m) is the weight-space right-hand side of the normal equations H x = rhs
        (data, prior constant, fixed neighbours, minus half the linear term); ``start`` a warm
        start (e.g. the clipped unbounded solve).
        """
        lo, hi, D = self.lower, self.upper, self.metric
        Z = np.clip(np.asarray(start, dtype=np.float64), lo, hi)
        N, m = Z.shape
        if N == 0:
            self.info = BoundedInfo(0, 0.0, 0.0, True, self.rho0, 0)
            return Z
        Uu = np.zeros_like(Z)  # scaled dual u
        rho, refactors, a = self.rho0, 0, self.relax
        g, V = self._modes_for(rho)
        factor = factor_modes(g, free, T)

        def step(Z, Uu):
            """One (over-relaxed) ADMM iteration from the state (z, u)."""
            b = rhs + rho * D * (Z - Uu)
            y, _ = dpttrs(*factor, (b @ V).T.reshape(-1, 1))
            X = y.reshape(m, N).T @ V.T
            Xr = a * X + (1.0 - a) * Z
            Zn = np.clip(Xr + Uu, lo, hi)
            return Zn, Uu + Xr - Zn, float(np.max(np.abs(X - Zn))), float(rho * np.max(np.abs(Zn - Z)))

        aa = _Anderson(self.memory) if self.memory > 0 else None
        s = np.concatenate([Z.ravel(), Uu.ravel()])
        Zn, Un, rp, rd = step(Z, Uu)
        fs = np.concatenate([Zn.ravel(), Un.ravel()])
        it, accepted = 1, 0
        while not (rp <= self.tol and rd <= self.tol) and it < self.max_iter:
            if it % self.adapt_every == 0 and rp > 0 and rd > 0:
                scale = float(np.clip(np.sqrt(rp / rd), 1e-3, 1e3))
                if scale > 5.0 or scale < 0.2:  # Boyd §3.4.1 / OSQP: balance the residuals, refactor
                    rho *= scale
                    g, V = self._modes_for(rho)
                    factor = factor_modes(g, free, T)
                    refactors += 1
                    Zn, Un = fs[:N * m].reshape(N, m), fs[N * m:].reshape(N, m) / scale  # rho D u unchanged
                    s = np.concatenate([Zn.ravel(), Un.ravel()])
                    Zn, Un, rp, rd = step(Zn, Un)
                    fs = np.concatenate([Zn.ravel(), Un.ravel()])
                    it += 1
                    if aa is not None:
                        aa.reset()
                    continue
            gs = fs - s
            nxt = fs
            if aa is not None and it >= self.accelerate_after:
                cand = aa.propose(s, gs)
                if cand is not None:  # safeguard: keep the extrapolation only if its residual is smaller
                    Zc, Uc, rpc, rdc = step(cand[:N * m].reshape(N, m), cand[N * m:].reshape(N, m))
                    it += 1
                    fc = np.concatenate([Zc.ravel(), Uc.ravel()])
                    if np.linalg.norm(fc - cand) < np.linalg.norm(gs):
                        s, fs, rp, rd = cand, fc, rpc, rdc
                        accepted += 1
                        continue
                    aa.reset()
            s = nxt
            Zn, Un, rp, rd = step(s[:N * m].reshape(N, m), s[N * m:].reshape(N, m))
            fs = np.concatenate([Zn.ravel(), Un.ravel()])
            it += 1
        Z = fs[:N * m].reshape(N, m)
        self.info = BoundedInfo(it, rp, rd, rp <= self.tol and rd <= self.tol, rho, refactors, accepted)
        return Z


class _Anderson:
    """Type-II Anderson acceleration of a fixed-point iteration s <- F(s) (Walker and Ni 2011; for
    ADMM/Douglas-Rachford with a residual safeguard: Zhang, O'Donoghue, Boyd 2020, "Globally
    convergent type-I Anderson acceleration for nonsmooth fixed-point iterations")."""

    def __init__(self, memory: int) -> None:
        self.memory = memory
        self.reset()

    def reset(self) -> None:
        self.s_prev = self.g_prev = None
        self.k = 0  # differences stored (ring buffer rows k % memory)
        self.dS = self.dG = None
        self.gram = np.zeros((self.memory, self.memory))

    def propose(self, s: np.ndarray, g: np.ndarray) -> np.ndarray | None:
        """Given the iterate s and its residual g = F(s) - s, the extrapolated next iterate (or None)."""
        M = self.memory
        if self.s_prev is not None:
            if self.dS is None:
                self.dS, self.dG = np.zeros((M, len(s))), np.zeros((M, len(s)))
            j = self.k % M
            np.subtract(s, self.s_prev, out=self.dS[j])
            np.subtract(g, self.g_prev, out=self.dG[j])
            self.k += 1
            col = self.dG @ self.dG[j]  # incremental Gram matrix dG dG^T
            self.gram[j, :] = col
            self.gram[:, j] = col
        self.s_prev, self.g_prev = s, g
        h = min(self.k, M)
        if h == 0:
            return None
        A = self.gram[:h, :h] + (1e-10 * np.trace(self.gram[:h, :h]) / h + 1e-300) * np.eye(h)
        try:
            gamma = np.linalg.solve(A, self.dG[:h] @ g)
        except np.linalg.LinAlgError:
            return None
        return s + g - gamma @ self.dS[:h] - gamma @ self.dG[:h]
