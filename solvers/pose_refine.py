"""Head pose fitted jointly with the expression, by alternation.

The "stable" markers are not rigid: they move with expression (ICT's nose bridge 1.6 mm with
browInnerUp), so a rigid fit to their neutral positions leaves the expression in the pose and the
pose error in every marker. Given solved weights, the basis predicts where the stable markers
should be; re-fitting the rigid correction to those predictions and solving again alternates
between pose and expression (block coordinate descent on one objective; Seol et al. 2012 §3.1
fit the pose to the neutral only, which is the first step of this).

Offline the correction is fitted on the *smoothed* markers (``pose_from``) and applied to the raw
ones: fitted on the raw stable markers it carries their noise into every marker as a rigid jitter,
which the smoother then reads as a larger marker noise (issue 15, ICT 0.5 mm: chosen noise 0.5 -> 0.7 mm,
blink peaks 0.63 -> 0.46).
"""

from __future__ import annotations

import numpy as np

from solvers.rigid import kabsch


def refit_pose(targets: np.ndarray, valid: np.ndarray, weights: np.ndarray, neutral: np.ndarray,
               stable: np.ndarray, basis: np.ndarray, pose_from: np.ndarray | None = None) -> np.ndarray:
    """Targets (T x n x 3, displacements from ``neutral`` in the head frame) moved by the rigid
    correction that best maps each frame's stable markers (of ``pose_from``, default the targets)
    onto neutral + basis @ weights."""
    out = np.array(targets, dtype=np.float64, copy=True)
    src = out if pose_from is None else np.asarray(pose_from, dtype=np.float64)
    stable = np.asarray(stable, bool)
    for t in range(len(out)):
        m = stable & valid[t]
        if m.sum() < 3:
            continue
        pred = (basis @ weights[t]).reshape(-1, 3)
        R, tr = kabsch((neutral + src[t])[m], (neutral + pred)[m])
        out[t] = np.where(valid[t][:, None], (neutral + out[t]) @ R.T + tr - neutral, 0.0)
    return out
