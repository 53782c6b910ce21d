"""Offline solve of a recorded take: stabilise every frame, then run a solver over the take."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from livecap.calibration import Profile
from livecap.stabilise import to_quaternion
from livecap.take import Take


@dataclass
class SolvedTake:
    names: list[str]
    weights: np.ndarray  # T x m
    head_rotation: np.ndarray  # T x 4 (x, y, z, w)
    head_translation: np.ndarray  # T x 3 mm
    targets: np.ndarray  # T x n x 3 stabilised displacements from the neutral
    valid: np.ndarray  # T x n
    rate: float
    first_frame: int
    solve_seconds: float


def prepare_targets(take: Take, profile: Profile):
    """Stabilised marker displacements from the actor's neutral, plus the head pose."""
    take = take.select(profile.labels)
    local, R, t = profile.stabiliser().stabilise(take.positions, take.valid)
    targets = np.where(take.valid[..., None], local - profile.source_neutral, 0.0)
    return take, targets, R, t


def solve_take(take: Take, profile: Profile, solver, progress=None) -> SolvedTake:
    """Run ``solver`` over every frame; solvers with ``solve(targets, valid)`` do it in one go."""
    take, targets, R, t = prepare_targets(take, profile)
    start = time.perf_counter()
    if hasattr(solver, "solve"):
        W = solver.solve(targets, take.valid)
    else:
        W = np.zeros((take.n_frames, len(profile.names)))
        for i in range(take.n_frames):
            W[i] = solver.step(targets[i], take.valid[i])
            if progress is not None:
                progress(i + 1, take.n_frames)
    elapsed = time.perf_counter() - start
    return SolvedTake(list(profile.names), W, to_quaternion(R), t, targets, take.valid, take.rate,
                      take.first_frame, elapsed)
