"""A peer's per-frame blendshape solve, as a baseline: NVIDIA Audio2Face-3D's published formulation (issue 41.7).

Reimplemented from its published terms and defaults (the SDK's ``blendshape_params``: L1 1, L2 3.5, symmetry 100,
temporal smoothing 5), not from its code. Per frame, with B the marker basis, s the stabilised displacement and
w_prev the previous frame's weights, bounded least squares

    min  |B w - s|^2 + sf [ L1^2/4 (1^T w)^2 + 10 L2 |w|^2 + 100 T |w - w_prev|^2 + 10 Sym sum_pairs (w_i - w_j)^2 ]
    subject to  lower <= w <= upper

(the L1 term enters squared: with non-negative weights it is (sum w)^2, a quadratic). ``sf`` scales the terms to
the face's size: the SDK uses (face bounding box / the template's)^2 with the template's meshes in cm and
thousands of vertices; on ~60 markers in mm the data term's scale is about the same (100 x per point, 1/100 the
points), so ``sf`` = 1 here. Symmetric pairs: names ending in _L/_R or Left/Right.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear


def symmetric_pairs(names: list[str]) -> list[tuple[int, int]]:
    where = {n: i for i, n in enumerate(names)}
    pairs = []
    for n, i in where.items():
        for a, b in (("_L", "_R"), ("Left", "Right")):
            if n.endswith(a) and n[: -len(a)] + b in where:
                pairs.append((i, where[n[: -len(a)] + b]))
    return pairs


class A2FSolve:
    """``step(target, valid)`` per frame (no latency); ``reset()`` forgets the previous frame."""

    def __init__(self, basis: np.ndarray, lower: np.ndarray, upper: np.ndarray, names: list[str], l1: float = 1.0,
                 l2: float = 3.5, symmetry: float = 100.0, temporal: float = 5.0, sf: float = 1.0) -> None:
        self.B = np.asarray(basis, float)
        m = self.B.shape[1]
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        S = np.zeros((0, m))
        for i, j in symmetric_pairs(names):
            row = np.zeros(m)
            row[i], row[j] = 1.0, -1.0
            S = np.vstack([S, row])
        self.temporal = sf * 100.0 * temporal
        self.R = sf * (0.25 * l1**2 * np.ones((m, m)) + 10.0 * l2 * np.eye(m) + 10.0 * symmetry * S.T @ S) \
            + self.temporal * np.eye(m)
        self.reset()

    def reset(self) -> None:
        self.prev = np.clip(np.zeros(self.B.shape[1]), self.lower, self.upper)

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        rows = np.repeat(np.asarray(valid, bool), 3)
        Bv, s = self.B[rows], np.asarray(target, float).reshape(-1)[rows]
        H = Bv.T @ Bv + self.R
        c = Bv.T @ s + self.temporal * self.prev
        L = np.linalg.cholesky(H)  # min w^T H w - 2 c^T w  ==  min |L^T w - L^-1 c|^2
        w = lsq_linear(L.T, np.linalg.solve(L, c), bounds=(self.lower, self.upper), method="bvls").x
        self.prev = w
        return w
