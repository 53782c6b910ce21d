"""Head pose fitted jointly with the expression: six rigid columns beside the blendshape basis.

The "stable" markers are not rigid: they move with expression (ICT's nose bridge 1.6 mm with
browInnerUp), so the stabiliser's rigid fit to their neutral positions leaves part of the
expression in the pose and the pose error in every marker (Seol et al. 2012 §3.1 fit the pose to
the neutral only). The residual correction is small (the stabiliser has removed the head motion),
so it is linearised about the stabilised frame: a small translation t and rotation w move neutral
marker p by t + w x (p - c), six columns that do not depend on the frame. Appended to the basis,
unbounded and outside the weights' prior, they make pose and expression ONE bounded least-squares
fit over all visible markers (Gauss-Newton's first step for the joint problem; Nocedal & Wright
2006 §10.3): the prior, not the few stable markers, decides what is expression and what is pose.

Each frame's correction is fitted from scratch, so it cannot accumulate. The alternation it
replaces (Kabsch of the stable markers onto the ones the solved expression predicts, then solve
again) had to carry its correction from frame to frame to pay, and carried in full it drifted to
17 degrees on a synthetic rig whose stable markers the shapes move (issue 15, docs/robustness.md).
Linearisation error: |w|^2 |p - c| / 2, 0.01 mm at 1 degree and 80 mm.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

N_POSE = 6  # translation x y z (mm), then rotation x y z (mm of arc at the markers' rms radius)


class RigidColumns:
    """The six rigid motions of the neutral markers (3n x 6), about their centroid ``c``; rotation
    columns scaled by the rms radius so that all six are in mm at the markers (a balanced Hessian)."""

    def __init__(self, neutral: np.ndarray) -> None:
        self.neutral = np.asarray(neutral, dtype=np.float64)
        self.centre = self.neutral.mean(0)
        p = self.neutral - self.centre
        self.radius = float(np.sqrt((p**2).sum(1).mean())) or 1.0
        J = np.zeros((len(p), 3, N_POSE))
        J[:, :, :3] = np.eye(3)
        J[:, :, 3:] = np.swapaxes(np.cross(np.eye(3)[None], p[:, None]), 1, 2) / self.radius  # e_k x p
        self.matrix = J.reshape(3 * len(p), N_POSE)

    def augment(self, basis: np.ndarray, lower: np.ndarray, upper: np.ndarray, mean: np.ndarray,
                precision: np.ndarray) -> tuple[np.ndarray, ...]:
        """Basis, limits, prior mean and precision of the joint fit: the pose unbounded, no prior on it."""
        m = np.shape(basis)[1]
        P = np.zeros((m + N_POSE, m + N_POSE))
        P[:m, :m] = precision
        inf = np.full(N_POSE, np.inf)
        return (np.hstack([basis, self.matrix]), np.r_[lower, -inf], np.r_[upper, inf],
                np.r_[mean, np.zeros(N_POSE)], P)

    def remove(self, targets: np.ndarray, valid: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Targets (T x n x 3, displacements from the neutral) with each frame's fitted rigid motion
        (T x 6) undone exactly (rotation by its rotation vector), 0 where invalid."""
        R = Rotation.from_rotvec(pose[:, 3:] / self.radius).as_matrix()
        q = self.neutral + np.asarray(targets, dtype=np.float64) - self.centre - pose[:, None, :3]
        out = np.einsum("tnj,tji->tni", q, R) + self.centre - self.neutral  # R^T q per frame
        return np.where(valid[..., None], out, 0.0)
