"""Accuracy metrics shared by tests, the CLI and the benchmarks.

Velocity error is Seol et al. 2012's objective, |D(BW)^T - DS^T|_F^2 (§4, Eq. 3), with D the
first difference in time; jitter is the mean absolute second difference of the weights.
"""

from __future__ import annotations

import numpy as np

from livecap.core.rig import Rig


def _velocity_residual(basis: np.ndarray, weights: np.ndarray, targets: np.ndarray,
                       valid: np.ndarray | None) -> np.ndarray:
    fit = weights @ basis.T
    d = np.diff(fit, axis=0) - np.diff(targets.reshape(len(targets), -1), axis=0)
    if valid is not None:  # a marker's velocity is known only where it is seen in both frames
        v = np.asarray(valid, dtype=bool)
        d = np.where(np.repeat(v[1:] & v[:-1], 3, axis=1), d, 0.0)
    return d


def velocity_error(basis: np.ndarray, weights: np.ndarray, targets: np.ndarray,
                   valid: np.ndarray | None = None) -> float:
    """|D (B W) - D S|_F^2 over a take: ``weights`` T x m, ``targets`` T x 3n (or T x n x 3).

    With ``valid`` (T x n) only marker velocities seen in both frames count.
    """
    return float(np.sum(_velocity_residual(basis, weights, targets, valid) ** 2))


def velocity_error_per_frame(basis: np.ndarray, weights: np.ndarray, targets: np.ndarray,
                             valid: np.ndarray | None = None) -> np.ndarray:
    d = _velocity_residual(basis, weights, targets, valid)
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


def range_excess(weights: np.ndarray, lower: float | np.ndarray, upper: float | np.ndarray) -> float:
    """How far the weights go outside [lower, upper] at worst (0 when inside)."""
    return float(max(np.max(lower - weights), np.max(weights - upper), 0.0))


def drift(errors: np.ndarray, rate: float, seconds: float = 60.0) -> tuple[float, float]:
    """RMS of a per-frame error series over its first and its last ``seconds`` (growth = drift)."""
    e = np.asarray(errors, dtype=np.float64)
    n = max(1, min(len(e), int(round(seconds * rate))))
    return float(np.sqrt(np.mean(e[:n] ** 2))), float(np.sqrt(np.mean(e[-n:] ** 2)))


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


def vertex_error_stats(rig: Rig, weights: np.ndarray, truth: np.ndarray, chunk: int = 256) -> dict[str, float]:
    """Vertex error (mm) of the rig posed by ``weights`` against ``truth``: ``mean`` over all vertices and
    frames, ``max``, and ``p95`` — the 95th percentile over frames of each frame's worst vertex, i.e. how
    bad the worst 5 % of frames look (users judge a solve by its worst frames)."""
    total, count, worst = 0.0, 0, []
    for i in range(0, len(weights), chunk):
        d = np.linalg.norm(rig.evaluate(weights[i:i + chunk]) - rig.evaluate(truth[i:i + chunk]), axis=2)
        total += float(d.sum())
        count += d.size
        worst.append(d.max(axis=1))
    w = np.concatenate(worst) if worst else np.zeros(1)
    return {"mean": total / max(count, 1), "p95": float(np.percentile(w, 95)), "max": float(w.max())}


def shape_indices(names: list[str], word: str) -> list[int]:
    """Shapes whose name contains ``word`` (any case): ``blink`` finds eyeBlinkLeft and eyeBlink_L."""
    return [i for i, n in enumerate(names) if word in n.lower()]


def peak_retention(solved: np.ndarray, truth: np.ndarray, indices: list[int], height: float | None = None,
                   window: int = 6) -> float:
    """Mean ratio of the solved peak (highest within +-``window`` frames) to each true peak >= ``height``
    of the given shapes (default: half the shapes' largest true value, at least 0.1): 1 keeps blinks
    closing and the jaw opening fully, < 1 shaves them. NaN when the truth has no such peak."""
    from scipy.signal import find_peaks

    if height is None:
        height = max(0.5 * float(np.max(truth[:, indices], initial=0.0)), 0.1)
    ratios = []
    for k in indices:
        peaks, _ = find_peaks(truth[:, k], height=height, distance=10)
        for p in peaks:
            ratios.append(solved[max(0, p - window):p + window + 1, k].max() / truth[p, k])
    return float(np.mean(ratios)) if ratios else float("nan")


def shape_bias(solved: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Mean signed error per shape (solved - truth): a shape the solve systematically over- or under-drives."""
    return np.mean(np.asarray(solved) - np.asarray(truth), axis=0)
