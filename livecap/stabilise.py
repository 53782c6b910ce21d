"""Head-motion removal (Seol et al. 2012 §3.1; Curio et al. 2006 §2.3).

Per frame, the rigid transform that best maps the stable markers onto their neutral positions
(Kabsch / Arun et al. 1987, SVD with the reflection guard). The removed motion is the head
pose, published with the weights. Convention: ``raw = R @ stabilised + t`` (head-to-world),
quaternions as (x, y, z, w).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising sum w_i |R src_i + t - dst_i|^2 (never a reflection).

    ``src``/``dst`` may be batched: (..., k, 3); ``weights`` (..., k).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    w = np.ones(src.shape[:-1]) if weights is None else np.asarray(weights, dtype=np.float64)
    wsum = w.sum(-1, keepdims=True)[..., None]
    cs = (w[..., None] * src).sum(-2, keepdims=True) / wsum
    cd = (w[..., None] * dst).sum(-2, keepdims=True) / wsum
    H = np.einsum("...ki,...kj->...ij", w[..., None] * (src - cs), dst - cd)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("...ij,...jk->...ik", U, Vt)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = np.einsum("...ji,...jk,...lk->...il", Vt, D, U)
    t = cd[..., 0, :] - np.einsum("...ij,...j->...i", R, cs[..., 0, :])
    return R, t


def to_quaternion(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_quat()


class HeadStabiliser:
    """Remove head motion frame by frame against a neutral reference of the markers."""

    def __init__(self, reference: np.ndarray, stable: np.ndarray) -> None:
        self.reference = np.asarray(reference, dtype=np.float64)
        self.stable = np.asarray(stable, dtype=bool)

    def pose(self, positions: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Head rotation and translation (head-to-world) for one frame or a batch (T, n, 3)."""
        use = valid & self.stable
        few = use.sum(-1) < 3
        use = np.where(few[..., None], valid, use)  # fewer than 3 stable markers: all visible ones
        ref = np.broadcast_to(self.reference, positions.shape)
        return kabsch(ref, positions, use.astype(np.float64))

    def stabilise(self, positions: np.ndarray, valid: np.ndarray):
        """Stabilised positions (same shape), rotation and translation."""
        R, t = self.pose(positions, valid)
        local = np.einsum("...ji,...nj->...ni", R, positions - t[..., None, :])
        return np.where(valid[..., None], local, 0.0), R, t
