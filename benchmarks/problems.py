"""Synthetic per-frame solve problems shaped like facial capture, shared by the per-frame benchmarks.

A marker basis whose columns are localised (each shape moves the markers near a random centre on a
face-sized patch, as sculpted blendshapes do), and a take of sparse, smooth weight curves: most
shapes rest at 0 most of the time (lower bounds active), a few go past 1 (upper bounds active), so
the bounded problems look like real frames rather than random dense ones.
"""

from __future__ import annotations

import numpy as np


def facial_basis(n_markers: int, n_shapes: int, rng: np.random.Generator) -> np.ndarray:
    """3n x m basis in mm per unit weight, each shape a Gaussian patch of marker motion."""
    sites = rng.uniform([-70, -80], [70, 60], (n_markers, 2))
    centres = rng.uniform([-60, -70], [60, 50], (n_shapes, 2))
    radius = rng.uniform(12, 35, n_shapes)
    direction = rng.normal(0, 1, (n_shapes, 3))
    direction *= rng.uniform(3, 9, (n_shapes, 1)) / np.linalg.norm(direction, axis=1, keepdims=True)
    d2 = ((sites[None] - centres[:, None]) ** 2).sum(-1)  # m x n
    fall = np.exp(-d2 / (2 * radius[:, None] ** 2))
    cols = fall[..., None] * direction[:, None, :]  # m x n x 3
    cols += rng.normal(0, 0.05, cols.shape)  # no two shapes exactly alike
    return cols.reshape(n_shapes, -1).T.copy()


def weight_take(n_frames: int, n_shapes: int, rng: np.random.Generator, rate: float = 120.0) -> np.ndarray:
    """T x m smooth, mostly-zero weight curves with occasional excursions past 1."""
    t = np.arange(n_frames) / rate
    W = np.zeros((n_frames, n_shapes))
    for k in range(n_shapes):
        for _ in range(max(1, int(rng.poisson(0.25 * t[-1] + 1)))):
            c, width, amp = rng.uniform(0, t[-1]), rng.uniform(0.1, 0.6), rng.uniform(0.2, 1.2)
            W[:, k] += amp * np.exp(-0.5 * ((t - c) / width) ** 2)
    return W


def frame_problems(n_markers: int, n_shapes: int, n_frames: int, seed: int = 0, noise_mm: float = 0.5):
    """(basis, targets T x 3n, true weights) for a take of ``n_frames`` frames."""
    rng = np.random.default_rng(seed)
    B = facial_basis(n_markers, n_shapes, rng)
    W = weight_take(n_frames, n_shapes, rng)
    S = W @ B.T + rng.normal(0, noise_mm, (n_frames, B.shape[0]))
    return B, S, W
