"""Accuracy metrics shared by tests, the CLI and the benchmarks.

Velocity error is Seol et al. 2012's objective, |D(BW)^T - DS^T|_F^2 (§4, Eq. 3), with D the
first difference in time; jitter is the mean absolute second difference of the weights.
"""

from __future__ import annotations

import numpy as np

from livecap.rig import Rig


def velocity_error(basis: np.ndarray, weights: np.ndarray, targets: np.ndarray) -> float:
    """|D (B W) - D S|_F^2 over a take: ``weights`` T x m, ``targets`` T x 3n."""
    fit = weights @ basis.T
    return float(np.sum((np.diff(fit, axis=0) - np.diff(targets.reshape(len(targets), -1), axis=0)) ** 2))


def velocity_error_per_frame(basis: np.ndarray, weights: np.ndarray, targets: np.ndarray) -> np.ndarray:
    fit = weights @ basis.T
    d = np.diff(fit, axis=0) - np.diff(targets.reshape(len(targets), -1), axis=0)
    return np.concatenate([[0.0], np.sum(d * d, axis=1)])


def position_error(basis: np.ndarray, weights: np.ndarray, targets: np.ndarray,
                   valid: np.ndarray | None = None) -> float:
    """RMS marker distance (mm) between the fitted sites and the targets, over visible markers."""
    fit = (weights @ basis.T).reshape(len(weights), -1, 3)
    dist = np.linalg.norm(fit - targets.reshape(fit.shape), axis=2)
    if valid is not None:
        dist = dist[valid]
    return float(np.sqrt(np.mean(dist**2)))


def weight_range(weights: np.ndarray) -> tuple[float, float]:
    return float(weights.min()), float(weights.max())


def jitter(weights: np.ndarray) -> float:
    """Mean |second difference| of the weight curves."""
    if len(weights) < 3:
        return 0.0
    return float(np.mean(np.abs(np.diff(weights, n=2, axis=0))))


def weight_rmse(weights: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean((weights - truth) ** 2)))


def vertex_error(rig: Rig, weights: np.ndarray, truth: np.ndarray, chunk: int = 256) -> tuple[float, float]:
    """Mean and max per-vertex distance (mm) between the rig posed by ``weights`` and by ``truth``."""
    total, count, worst = 0.0, 0, 0.0
    for i in range(0, len(weights), chunk):
        d = np.linalg.norm(rig.evaluate(weights[i:i + chunk]) - rig.evaluate(truth[i:i + chunk]), axis=2)
        total += float(d.sum())
        count += d.size
        worst = max(worst, float(d.max()))
    return total / max(count, 1), worst
