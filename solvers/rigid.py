"""Rigid and similarity fits between corresponding point sets (Arun et al. 1987; Umeyama 1991).

Shared by head stabilisation (Seol et al. 2012 §3.1), calibration's proportion matching (§3.2),
rig transfer and the viewer's placement of the rig in the actor's head frame.
"""

from __future__ import annotations

import numpy as np


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising sum w_i |R src_i + t - dst_i|^2 (never a reflection).

    ``src``/``dst`` may be batched: (..., k, 3); ``weights`` (..., k). All-zero weights give the
    identity rotation rather than NaN.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    w = np.ones(src.shape[:-1]) if weights is None else np.asarray(weights, dtype=np.float64)
    if src.ndim == 2 and dst.ndim == 2 and w.ndim == 1:
        return _kabsch_one(src, dst, w)
    wsum = np.maximum(w.sum(-1), 1e-300)[..., None]
    cs = (w[..., None, :] @ src)[..., 0, :] / wsum
    cd = (w[..., None, :] @ dst)[..., 0, :] / wsum
    H = np.swapaxes(src - cs[..., None, :], -1, -2) @ (w[..., None] * (dst - cd[..., None, :]))
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    Vt[..., 2, :] *= np.where(d == 0, 1.0, d)[..., None]  # reflection guard: flip the smallest axis
    R = np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)
    t = cd - (R @ cs[..., None])[..., 0]
    return R, t


def _kabsch_one(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Single-frame Kabsch with few numpy calls (the streaming path)."""
    ws = w.sum()
    if ws <= 0:
        return np.eye(3), np.zeros(3)
    cs = (w @ src) / ws
    cd = (w @ dst) / ws
    H = (src - cs).T @ ((dst - cd) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    R = Vt.T @ U.T
    if np.linalg.det(R) < 0:  # reflection guard: flip the axis of the smallest singular value
        Vt[2] = -Vt[2]
        R = Vt.T @ U.T
    return R, cd - R @ cs


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale, rotation, translation with s R src + t ~ dst (Umeyama 1991)."""
    R, _ = kabsch(src, dst)
    cs, cd = src.mean(0), dst.mean(0)
    s = np.sum((dst - cd) * ((src - cs) @ R.T)) / np.sum((src - cs) ** 2)
    return float(s), R, cd - s * R @ cs
