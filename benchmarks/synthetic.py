"""Synthetic problems at any size (n markers x m shapes), for scaling figures.

Markers sit on a face-sized ellipsoid cap; each shape moves a Gaussian neighbourhood of markers
by a random vector, as sculpted local shapes do, so conditioning resembles a real rig's.
"""

from __future__ import annotations

import numpy as np

from livecap.calibration import Profile


def synthetic_profile(n_markers: int, n_shapes: int, seed: int = 0) -> Profile:
    rng = np.random.default_rng(seed)
    th = rng.uniform(-1.2, 1.2, n_markers)
    ph = rng.uniform(-0.9, 0.9, n_markers)
    sites = np.stack([75 * np.sin(th) * np.cos(ph), 110 * np.sin(ph), 95 * np.cos(th) * np.cos(ph)], 1)
    centres = sites[rng.integers(0, n_markers, n_shapes)] + rng.normal(0, 5, (n_shapes, 3))
    radius = rng.uniform(12, 35, n_shapes)
    d2 = ((sites[None] - centres[:, None]) ** 2).sum(-1)
    fall = np.exp(-0.5 * d2 / radius[:, None] ** 2)  # m x n
    vec = rng.normal(0, 4, (n_shapes, 3))
    deltas = fall[..., None] * vec[:, None, :]
    basis = np.transpose(deltas, (1, 2, 0)).reshape(3 * n_markers, n_shapes)
    stable = np.zeros(n_markers, bool)
    stable[np.argsort(-sites[:, 1])[:4]] = True
    return Profile([f"m{i}" for i in range(n_markers)], [f"s{k}" for k in range(n_shapes)], sites, stable, basis,
                   np.zeros(n_shapes), np.ones(n_shapes), sites.copy(), {"synthetic": True})


def synthetic_stream(profile: Profile, n_frames: int, noise_mm: float = 0.3, seed: int = 1):
    """Targets (T x n x 3) from smooth sparse weight curves plus noise, and all-valid masks."""
    rng = np.random.default_rng(seed)
    m = profile.basis.shape[1]
    t = np.arange(n_frames)[:, None]
    freq = rng.uniform(0.002, 0.02, m)
    active = rng.random(m) < min(1.0, 8.0 / m * 4)
    W = np.clip(np.sin(2 * np.pi * freq * t + rng.uniform(0, 6.3, m)), 0, 1) * active
    targets = (W @ profile.basis.T).reshape(n_frames, -1, 3) + rng.normal(0, noise_mm, (n_frames, profile.n_markers, 3))
    return targets, np.ones((n_frames, profile.n_markers), bool), W
