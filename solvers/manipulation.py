"""Direct manipulation of blendshape weights: pins on the face -> bounded weights.

Lewis & Anjyo 2010 ("Direct manipulation blendshapes"; Lewis et al. 2014 §5.5.2): the artist
drags points of the face and the weights that best put them there are solved, regularised by the
"least surprise" principle that the weights change as little as possible:

    minimise  sum_p |r_p + D_p w - g_p|^2 + pull |w - w_cur|^2     subject to  lower <= w <= upper

with r_p the pinned point at rest, D_p its rows of the delta basis (3 x m), g_p the goal. For one
pin set the Hessian H = D^T D + pull I is constant, so it is prepared (Cholesky) once; a drag step
changes only the right-hand side. The box is handled by a primal active-set method whose free-set
systems are small (at most m x m) and whose start is the clipped unconstrained solution, so most
steps need no more than one or two sub-solves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg


@dataclass(frozen=True)
class ManipulationSettings:
    """``pull``: weight (mm^2 per unit weight^2) of staying at the current weights (LA10's prior);
    ``max_iter``: active-set iterations before giving up (the last feasible iterate is returned)."""

    pull: float = 1.0
    max_iter: int = 200
    tol: float = 1e-10


class DirectManipulation:
    """Prepared for one set of pinned points; ``step(goals, current)`` solves a drag.

    ``rest``: (P, 3) the pinned points with all weights zero; ``deltas``: (m, P, 3) how each shape
    moves them (the linear part of the rig at those points).
    """

    def __init__(self, rest: np.ndarray, deltas: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                 settings: ManipulationSettings | None = None) -> None:
        self.settings = settings or ManipulationSettings()
        if self.settings.pull <= 0:
            raise ValueError("manipulation pull must be > 0 (it keeps the pin problem well posed)")
        deltas = np.asarray(deltas, dtype=np.float64)
        m = deltas.shape[0]
        self.rest = np.asarray(rest, dtype=np.float64).reshape(-1)
        self.A = deltas.reshape(m, -1).T  # 3P x m
        if self.A.shape[0] != self.rest.size:
            raise ValueError(f"pins: {self.rest.size // 3} rest points but deltas for {self.A.shape[0] // 3}")
        self.lower = np.broadcast_to(np.asarray(lower, dtype=np.float64), (m,)).copy()
        self.upper = np.broadcast_to(np.asarray(upper, dtype=np.float64), (m,)).copy()
        self.H = self.A.T @ self.A + self.settings.pull * np.eye(m)
        self._chol = scipy.linalg.cho_factor(self.H)
        self.iterations = 0

    @property
    def n_shapes(self) -> int:
        return self.H.shape[0]

    def objective(self, w: np.ndarray, goals: np.ndarray, current: np.ndarray) -> float:
        r = self.rest + self.A @ w - np.asarray(goals, dtype=np.float64).reshape(-1)
        return float(r @ r + self.settings.pull * np.sum((w - current) ** 2))

    def step(self, goals: np.ndarray, current: np.ndarray) -> np.ndarray:
        """Weights inside the limits that best put the pins at ``goals`` (P x 3) near ``current``."""
        current = np.asarray(current, dtype=np.float64)
        b = self.A.T @ (np.asarray(goals, dtype=np.float64).reshape(-1) - self.rest) + self.settings.pull * current
        w = scipy.linalg.cho_solve(self._chol, b)
        lo, hi = self.lower, self.upper
        if np.all((w >= lo) & (w <= hi)):
            self.iterations = 0
            return w
        return self._active_set(b, np.clip(w, lo, hi))

    def _active_set(self, b: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Primal active-set method for min x^T H x - 2 b^T x in the box (Nocedal & Wright §16.5)."""
        H, lo, hi, tol = self.H, self.lower, self.upper, self.settings.tol
        at_lo, at_hi = x <= lo, x >= hi
        for it in range(1, self.settings.max_iter + 1):
            free = ~(at_lo | at_hi)
            g = H @ x - b  # half the gradient
            p = np.zeros_like(x)
            if free.any():
                p[free] = np.linalg.solve(H[np.ix_(free, free)], -g[free])
            if np.max(np.abs(p), initial=0.0) <= tol * (1.0 + np.max(np.abs(x))):
                # multipliers: at the lower bound the gradient must point inwards (g >= 0), at the upper g <= 0
                wrong = np.where(at_lo, -g, 0.0) + np.where(at_hi, g, 0.0)
                j = int(np.argmax(wrong))
                if wrong[j] <= tol * (1.0 + np.max(np.abs(b))):
                    self.iterations = it
                    return x
                at_lo[j] = at_hi[j] = False
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                to_lo = np.where(p < 0, (lo - x) / p, np.inf)
                to_hi = np.where(p > 0, (hi - x) / p, np.inf)
            reach = np.minimum(to_lo, to_hi)
            reach[~free] = np.inf
            j = int(np.argmin(reach))
            alpha = min(1.0, float(reach[j]))
            x = x + alpha * p
            if alpha < 1.0:
                if to_lo[j] <= to_hi[j]:
                    x[j], at_lo[j] = lo[j], True
                else:
                    x[j], at_hi[j] = hi[j], True
        self.iterations = self.settings.max_iter
        return np.clip(x, lo, hi)
