"""Head-motion removal (Seol et al. 2012 §3.1; Curio et al. 2006 §2.3).

Per frame, the rigid transform that best maps the stable markers onto their neutral positions
(Kabsch / Arun et al. 1987, SVD with the reflection guard). The removed motion is the head
pose, published with the weights. Convention: ``raw = R @ stabilised + t`` (head-to-world),
quaternions as (x, y, z, w).
"""

from __future__ import annotations

import numpy as np


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
    """Unit quaternion(s) (x, y, z, w) of rotation matrices (..., 3, 3).

    The same branch-on-the-largest-component method (Shepperd 1978) and sign as
    ``scipy.spatial.transform.Rotation.from_matrix(R).as_quat()``, in plain numpy: the live
    pipeline calls this every frame, and scipy's version costs ~0.25 ms per single matrix.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.ndim > 3:
        return to_quaternion(R.reshape(-1, 3, 3)).reshape(*R.shape[:-2], 4)
    if R.ndim == 2:  # one matrix (every live frame): plain floats, no masks
        m = R.tolist()
        tr = m[0][0] + m[1][1] + m[2][2]
        diag = [m[0][0], m[1][1], m[2][2], tr]
        i = diag.index(max(diag))
        q = [0.0, 0.0, 0.0, 0.0]
        if i == 3:
            q = [m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1], 1 + tr]
        else:
            j, k = (i + 1) % 3, (i + 2) % 3
            q[i] = 1 - tr + 2 * m[i][i]
            q[j] = m[j][i] + m[i][j]
            q[k] = m[k][i] + m[i][k]
            q[3] = m[k][j] - m[j][k]
        out = np.array(q)
        return out / np.sqrt(out @ out)
    d0, d1, d2 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    tr = d0 + d1 + d2
    choice = np.argmax(np.stack([d0, d1, d2, tr], 1), 1)
    q = np.empty((len(R), 4))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        sel = choice == i
        q[sel, i] = 1 - tr[sel] + 2 * R[sel, i, i]
        q[sel, j] = R[sel, j, i] + R[sel, i, j]
        q[sel, k] = R[sel, k, i] + R[sel, i, k]
        q[sel, 3] = R[sel, k, j] - R[sel, j, k]
    sel = choice == 3
    q[sel, 0] = R[sel, 2, 1] - R[sel, 1, 2]
    q[sel, 1] = R[sel, 0, 2] - R[sel, 2, 0]
    q[sel, 2] = R[sel, 1, 0] - R[sel, 0, 1]
    q[sel, 3] = 1 + tr[sel]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


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
