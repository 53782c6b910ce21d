"""Per-frame bounded least squares: the plain baseline every other mode is compared against.

minimise |B w - s|^2 + lam |w|^2 subject to lower <= w <= upper, rows of missing markers
dropped (the per-frame fit of Chuang & Bregler 2002 and Curio et al. 2006 §2.3, without their
refinements).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear


class BoundedLeastSquares:
    def __init__(self, basis: np.ndarray, lower: np.ndarray, upper: np.ndarray, ridge: float = 0.0) -> None:
        self.basis = np.asarray(basis, dtype=np.float64)
        self.lower = np.asarray(lower, dtype=np.float64)
        self.upper = np.asarray(upper, dtype=np.float64)
        self.ridge = float(ridge)
        m = self.basis.shape[1]
        self._reg = np.sqrt(self.ridge) * np.eye(m)
        self._last = np.clip(np.zeros(m), self.lower, self.upper)

    def reset(self) -> None:
        self._last = np.clip(np.zeros_like(self._last), self.lower, self.upper)

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        rows = np.repeat(np.asarray(valid, dtype=bool), 3)
        if not rows.any():
            return self._last.copy()
        A = self.basis[rows]
        b = np.asarray(target, dtype=np.float64).reshape(-1)[rows]
        if self.ridge > 0:
            A = np.vstack([A, self._reg])
            b = np.concatenate([b, np.zeros(len(self._reg))])
        res = lsq_linear(A, b, bounds=(self.lower, self.upper), method="bvls")
        self._last = res.x
        return res.x.copy()
