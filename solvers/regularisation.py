"""Regularisation chosen from data, and the bounded prior least-squares solve that uses it.

The per-frame fit ``|B w - s|^2`` is ill-conditioned for real rigs seen through ~60 markers
(Lewis et al. 2014 §5.2: blendshape bases are far from orthogonal), so marker noise is amplified
along B's small singular directions. A Tikhonov term ``lam |w|^2`` trades that variance for
bias; how much is a property of the rig, the marker layout and the noise, so it is selected
from data, deterministically, by either

* generalised cross-validation (Golub, Heath & Wahba 1979): ``GCV(lam) = N |r(lam)|^2 /
  (N - tr H(lam))^2`` summed over frames, computed for every ``lam`` at once from the SVD of B;
* K-fold cross-validation on held-out markers: markers are split into K fixed folds (marker i
  in fold i mod K); each fold's displacements are predicted from a fit to the other markers.
  Unlike GCV this sees the calibration's model error (the actor is not the rig), not only
  noise.

The noise level itself comes from the take (``estimate_noise``): the median absolute second
difference of the marker channels, which white noise dominates at capture rates (a smooth
motion's second difference is tiny at 120 Hz). ``fit_residual`` adds what that misses: the part of the
markers the rig cannot explain, per marker.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solvers.qp import FrameQP

DEFAULT_GRID = np.logspace(-2, 4, 25)


def estimate_noise(targets: np.ndarray, valid: np.ndarray) -> float:
    """Per-coordinate marker noise sigma (mm) from the second differences of a take.

    For white noise of sigma, the second difference has std sqrt(6) sigma; the median absolute
    value (MAD / 0.6745) ignores the few frames where the face really accelerates.
    """
    X = np.asarray(targets, dtype=np.float64)
    ok = np.asarray(valid, dtype=bool)
    if len(X) < 3:
        raise ValueError("noise estimate needs at least 3 frames")
    d2 = X[2:] - 2 * X[1:-1] + X[:-2]
    both = ok[2:] & ok[1:-1] & ok[:-2]
    vals = np.abs(d2[both]).ravel()
    if vals.size == 0:
        raise ValueError("noise estimate needs a marker visible for 3 consecutive frames")
    return float(np.median(vals) / 0.6745 / np.sqrt(6.0))


def fit_residual(basis: np.ndarray, targets: np.ndarray, valid: np.ndarray, ridge: float,
                 max_frames: int = 600) -> np.ndarray:
    """Per marker, the sd per coordinate (mm) of what the rig cannot explain: the ridge fit's residual over the take's
    fully visible frames, divided by the share of white noise that survives the fit (``diag((I - H)^2)``, H the
    ridge hat matrix), so that pure white noise of sigma reads sigma and model mismatch reads above it.

    The second-difference estimate (``estimate_noise``) sees only frame-to-frame noise: on smoothed or interpolated
    captures it reads ~0 while the rig misses the actor's face by millimetres (issue 35.2)."""
    B = np.asarray(basis, dtype=np.float64)
    S = _full_frames(targets, valid, max_frames)
    M = np.eye(B.shape[0]) - B @ np.linalg.solve(B.T @ B + max(float(ridge), 1e-9) * np.eye(B.shape[1]), B.T)
    R = S @ M  # M is symmetric
    n = B.shape[0] // 3
    seen = np.mean(R * R, axis=0).reshape(n, 3).sum(axis=1)
    share = np.sum(M * M, axis=0).reshape(n, 3).sum(axis=1)  # diag(M^2) = column norms of the symmetric M
    return np.sqrt(seen / np.maximum(share, 0.05))


@dataclass
class Selection:
    """A selected value, the criterion over the grid, and how it was chosen (for the report)."""

    value: float
    grid: np.ndarray
    scores: np.ndarray
    criterion: str

    def as_dict(self) -> dict:
        return {"value": float(self.value), "criterion": self.criterion,
                "grid": [float(g) for g in self.grid], "scores": [float(s) for s in self.scores]}


def _full_frames(targets: np.ndarray, valid: np.ndarray, max_frames: int) -> np.ndarray:
    """Frames with every marker visible, evenly thinned to at most ``max_frames`` (deterministic)."""
    S = np.asarray(targets, dtype=np.float64).reshape(len(targets), -1)
    full = np.asarray(valid, dtype=bool).all(axis=1)
    if not full.any():
        raise ValueError("regularisation selection needs frames with every marker visible")
    S = S[full]
    if len(S) > max_frames:
        S = S[np.linspace(0, len(S) - 1, max_frames).round().astype(int)]
    return S


def gcv_ridge(basis: np.ndarray, targets: np.ndarray, valid: np.ndarray, grid: np.ndarray = DEFAULT_GRID,
              max_frames: int = 2000) -> Selection:
    """Ridge lam minimising generalised cross-validation over the take's fully visible frames."""
    B = np.asarray(basis, dtype=np.float64)
    S = _full_frames(targets, valid, max_frames)
    U, s, _ = np.linalg.svd(B, full_matrices=False)
    C = S @ U  # T x r coefficients on the column space
    outside = np.sum(S * S, axis=1) - np.sum(C * C, axis=1)  # |s_perp|^2, untouched by any lam
    N = B.shape[0]
    scores = []
    for lam in grid:
        shrink = lam / (s * s + lam)
        resid = np.sum((C * shrink) ** 2, axis=1) + outside
        dof = N - np.sum(s * s / (s * s + lam))
        scores.append(N * resid.mean() / dof**2)
    scores = np.asarray(scores)
    return Selection(float(grid[int(np.argmin(scores))]), np.asarray(grid, float), scores, "gcv")


def holdout_ridge(basis: np.ndarray, targets: np.ndarray, valid: np.ndarray, grid: np.ndarray = DEFAULT_GRID,
                  folds: int = 5, lower: np.ndarray | None = None, upper: np.ndarray | None = None,
                  max_frames: int = 600) -> Selection:
    """Ridge lam minimising the error of predicting held-out markers (K fixed folds).

    The fit to the kept markers is the ridge solution clipped to the weight limits (the same
    estimate the per-frame solvers make, without their active-set cost).
    """
    B = np.asarray(basis, dtype=np.float64)
    S = _full_frames(targets, valid, max_frames)
    n = B.shape[0] // 3
    m = B.shape[1]
    lo = np.full(m, -np.inf) if lower is None else np.asarray(lower, float)
    hi = np.full(m, np.inf) if upper is None else np.asarray(upper, float)
    fold_of = np.repeat(np.arange(n) % folds, 3)
    scores = np.zeros(len(grid))
    for k in range(folds):
        keep, out = fold_of != k, fold_of == k
        A = B[keep]
        G, R = A.T @ A, S[:, keep] @ A  # T x m right-hand sides
        for g, lam in enumerate(grid):
            W = np.clip(np.linalg.solve(G + lam * np.eye(m), R.T).T, lo, hi)
            scores[g] += np.sum((W @ B[out].T - S[:, out]) ** 2)
    scores /= S.size
    best = float(grid[int(np.argmin(scores))])
    return Selection(best, np.asarray(grid, float), scores, f"{folds}-fold held-out markers")


class PriorLeastSquares(FrameQP):
    """Bounded per-frame fit with a Gaussian prior and a rest-pull (Tikhonov, generalised).

    minimise  |B_v w - s_v|^2 + (w - p)^T R (w - p) + mu^T w    subject to lower <= w <= upper

    with B_v the rows of visible markers, R = diag(ridge) + prior (m x m, e.g. a shape-tying
    matrix from ``solvers.observability``), p the prior mean and mu >= 0 a per-shape pull toward
    rest: with w >= 0 it is an L1 penalty, so a shape whose evidence is below its noise floor
    stays exactly at rest instead of jittering (the sparse fits discussed in Lewis et al. 2014
    §5.2). It is the per-frame QP of ``solvers.qp.FrameQP`` (prefactored DAQP workspace per marker-
    visibility pattern, warm-started active set) with R as its prior and mu/2 as its linear term.
    """

    def __init__(self, basis: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                 ridge: float | np.ndarray = 0.0, prior: np.ndarray | None = None,
                 mean: np.ndarray | None = None, rest_pull: np.ndarray | float = 0.0) -> None:
        basis = np.asarray(basis, dtype=np.float64)
        m = basis.shape[1]
        R = np.diag(np.broadcast_to(np.asarray(ridge, dtype=np.float64), (m,)).copy())
        if prior is not None:
            R = R + np.asarray(prior, dtype=np.float64)
        mean = np.zeros(m) if mean is None else np.asarray(mean, dtype=np.float64)
        super().__init__(basis, lower, upper, prior=(mean, R), prior_weight=1.0)
        self.rest_pull = rest_pull

    @property
    def rest_pull(self) -> np.ndarray:
        return 2.0 * self.linear

    @rest_pull.setter
    def rest_pull(self, value: np.ndarray | float) -> None:
        self.linear = 0.5 * np.broadcast_to(np.asarray(value, dtype=np.float64), (self.m,)).copy()

    @property
    def _last(self) -> np.ndarray:
        return self._prev
