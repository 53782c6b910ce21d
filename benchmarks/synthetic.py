"""Synthetic problems at any size (n markers x m shapes), shaped like facial capture, shared by every
per-frame benchmark.

Markers sit on a face-sized ellipsoid cap; each shape moves a Gaussian neighbourhood of markers
by a random vector, as sculpted local shapes do, so conditioning resembles a real rig's. Weight
curves are smooth bumps that mostly rest at 0 (lower bounds active) and sometimes pass 1 (upper
bounds active), so bounded problems look like real frames rather than random dense ones.
"""

from __future__ import annotations

import numpy as np

from livecap.calibration.profile import Profile


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
    deltas += rng.normal(0, 0.05, deltas.shape)  # no two shapes exactly alike
    basis = np.transpose(deltas, (1, 2, 0)).reshape(3 * n_markers, n_shapes)
    stable = np.zeros(n_markers, bool)
    stable[np.argsort(-sites[:, 1])[:4]] = True
    return Profile([f"m{i}" for i in range(n_markers)], [f"s{k}" for k in range(n_shapes)], sites, stable, basis,
                   np.zeros(n_shapes), np.ones(n_shapes), sites.copy(), {"synthetic": True})


def weight_take(n_frames: int, n_shapes: int, rng: np.random.Generator, rate: float = 120.0,
                moving: int | None = None) -> np.ndarray:
    """T x m smooth, mostly-zero weight curves with occasional excursions past 1.

    ``moving``: how many shapes ever move (a random subset; default all), since a performance
    uses a few dozen shapes at a time even on a 1000-shape rig."""
    t = np.arange(n_frames) / rate
    W = np.zeros((n_frames, n_shapes))
    which = np.arange(n_shapes) if moving is None or moving >= n_shapes else rng.choice(n_shapes, moving, False)
    for k in which:
        for _ in range(max(1, int(rng.poisson(0.25 * t[-1] + 1)))):
            c, width, amp = rng.uniform(0, t[-1]), rng.uniform(0.1, 0.6), rng.uniform(0.2, 1.2)
            W[:, k] += amp * np.exp(-0.5 * ((t - c) / width) ** 2)
    return W


def synthetic_stream(profile: Profile, n_frames: int, noise_mm: float = 0.3, seed: int = 1, moving: int = 40):
    """Targets (T x n x 3) from ``weight_take`` curves plus noise, all-valid masks (T x n), weights."""
    rng = np.random.default_rng(seed)
    W = weight_take(n_frames, profile.basis.shape[1], rng, moving=moving)
    targets = (W @ profile.basis.T).reshape(n_frames, -1, 3) + rng.normal(0, noise_mm, (n_frames, profile.n_markers, 3))
    return targets, np.ones((n_frames, profile.n_markers), bool), W


def frame_problems(n_markers: int, n_shapes: int, n_frames: int, seed: int = 0, noise_mm: float = 0.5):
    """(basis 3n x m, targets T x 3n, true weights T x m) for a take of ``n_frames`` frames."""
    profile = synthetic_profile(n_markers, n_shapes, seed)
    targets, _, W = synthetic_stream(profile, n_frames, noise_mm, seed + 1, moving=n_shapes)
    return profile.basis, targets.reshape(n_frames, -1), W


def rom_keys(profile: Profile, noise_mm: float = 0.3, seed: int = 2):
    """A synthetic range-of-motion key set for the RBF mode (Pyun et al. 2003 §3): the neutral plus
    one key per shape at full weight, its marker displacement the shape's plus noise."""
    from livecap.calibration.keys import KeySet

    rng = np.random.default_rng(seed)
    m, n = profile.basis.shape[1], profile.n_markers
    target = np.vstack([np.zeros(m), np.eye(m)])
    source = (target @ profile.basis.T).reshape(m + 1, n, 3) + rng.normal(0, noise_mm, (m + 1, n, 3))
    source[0] = 0.0
    return KeySet(["neutral", *profile.names], list(range(m + 1)), source, np.ones((m + 1, n), bool), target,
                  list(profile.names))
