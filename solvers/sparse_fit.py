"""Sparse per-frame fit: shapes at rest stay exactly at rest until the markers say otherwise.

Blendshape weights are sparse (most shapes rest in most frames) and non-negative, so an L1
penalty ``mu^T w`` is a linear term of the bounded QP (Lewis et al. 2014 §5.2 on sparse fits;
Tibshirani 1996, the lasso). Its scale comes from the noise, not from tuning: at ``w_k = 0`` the
KKT condition keeps shape k at rest while ``b_k^T r <= mu_k / 2`` (r the residual), and under
white marker noise of sigma per coordinate ``b_k^T noise ~ N(0, sigma^2 |b_k|^2)``. So
``mu_k = 2 z sigma |b_k|`` keeps a resting shape at rest unless its evidence exceeds z noise
standard deviations; ``z = sqrt(2 ln m)`` is the universal threshold (Donoho & Johnstone 1994),
under which no more than a handful of m resting shapes cross per frame.

A soft threshold also shrinks active shapes by ``z`` noise sd. ``HysteresisSparseFit`` uses
two thresholds: a shape *enters* at ``z_enter`` and, once active (weight > 0 in the previous
frame), *stays* under the smaller ``z_stay``, so blinks keep their amplitude while resting shapes
do not flicker. ``holdout_sparse_ridge`` selects the small ridge that remains (for the
poorly observed blends the L1 term does not fix) by cross-validation on held-out markers,
with the same estimator the stream uses.
"""

from __future__ import annotations

import numpy as np

from solvers.regularisation import PriorLeastSquares, Selection, _full_frames


def universal_threshold(m: int) -> float:
    """sqrt(2 ln m): the largest of m standard normals stays below it with high probability."""
    return float(np.sqrt(2.0 * np.log(max(int(m), 2))))


def l1_weights(basis: np.ndarray, noise_mm: float, z: float) -> np.ndarray:
    """Linear-term coefficients ``mu_k = 2 z sigma |b_k|`` (the QP is ``w^T H w / 2``-scaled as
    ``|Bw - s|^2``, whose gradient at rest is ``-2 b_k^T s``)."""
    return 2.0 * float(z) * float(noise_mm) * np.linalg.norm(np.asarray(basis, dtype=np.float64), axis=0)


class HysteresisSparseFit(PriorLeastSquares):
    """``|B_v w - s_v|^2 + ridge |w|^2 + mu(state)^T w``, bounds; ``mu`` = ``enter`` for shapes at
    rest in the previous frame, ``stay`` for active ones. ``reset()`` puts every shape at rest."""

    def __init__(self, basis: np.ndarray, lower: np.ndarray, upper: np.ndarray, ridge: float | np.ndarray,
                 enter: np.ndarray, stay: np.ndarray) -> None:
        super().__init__(basis, lower, upper, ridge, rest_pull=enter)
        m = self.basis.shape[1]
        self.enter = np.broadcast_to(np.asarray(enter, dtype=np.float64), (m,)).copy()
        self.stay = np.broadcast_to(np.asarray(stay, dtype=np.float64), (m,)).copy()
        if np.any(self.enter < 0) or np.any(self.stay < 0):
            raise ValueError("L1 thresholds must be non-negative")
        self._rest = np.clip(0.0, self.lower, self.upper)
        self._half = (0.5 * self.enter, 0.5 * self.stay)
        self._gap = np.empty(m)

    def _update_linear(self) -> None:
        gap = np.abs(np.subtract(self._prev, self._rest, out=self._gap), out=self._gap)
        self.linear = np.where(gap <= 1e-9, *self._half)  # the L1 term at rest, the smaller one once active


SPARSE_GRID = np.logspace(-1, 2, 7)


def holdout_sparse_ridge(basis: np.ndarray, targets: np.ndarray, valid: np.ndarray, noise_mm: float, z: float,
                         lower: np.ndarray, upper: np.ndarray, grid: np.ndarray = SPARSE_GRID, folds: int = 5,
                         max_frames: int = 240) -> Selection:
    """Ridge of the sparse fit minimising the error of predicting held-out markers (K fixed folds,
    marker i in fold i mod K, evenly thinned fully visible frames: deterministic)."""
    B = np.asarray(basis, dtype=np.float64)
    S = _full_frames(targets, valid, max_frames)
    n = B.shape[0] // 3
    fold_of = np.repeat(np.arange(n) % folds, 3)
    scores = np.zeros(len(grid))
    for k in range(folds):
        keep, out = fold_of != k, fold_of == k
        A = B[keep]
        mu = l1_weights(A, noise_mm, z)
        seen = np.ones(int(keep.sum()) // 3, bool)
        for g, lam in enumerate(grid):
            fit = PriorLeastSquares(A, lower, upper, float(lam), rest_pull=mu)
            W = np.array([fit.step(s[keep].reshape(-1, 3), seen) for s in S])
            scores[g] += np.sum((W @ B[out].T - S[:, out]) ** 2)
    scores /= S.size
    return Selection(float(grid[int(np.argmin(scores))]), np.asarray(grid, float), scores,
                     f"{folds}-fold held-out markers, sparse fit")
