"""Plausibility of a solve on a real capture, where no ground truth exists (issue 35).

What a solve should show is judged from the markers themselves: a still, near-neutral face gives
weights near zero; a shape whose markers do not move stays quiet; the main shapes follow the
marker geometry that defines them (the chin drops -> jawOpen; the mouth corners rise and widen ->
smile; the brows rise -> brow raise); weights do not jump between single frames. Every function
takes the solved weights (T x m) and, where needed, the stabilised marker displacements from the
neutral (``SolvedTake.targets``, T x n x 3, head frame, mm).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

GAZE = re.compile(r"eyeLook", re.IGNORECASE)


def weight_sum(weights: np.ndarray, frames: slice) -> tuple[float, float]:
    """(mean, max) over ``frames`` of the per-frame sum of weights: near 0 on a near-neutral span."""
    s = np.asarray(weights)[frames].sum(axis=1)
    return float(s.mean()), float(s.max())


def shape_markers(basis: np.ndarray, threshold_mm: float = 1.0) -> list[np.ndarray]:
    """Per shape, the markers it moves by more than ``threshold_mm`` at full weight (basis 3n x m)."""
    n = basis.shape[0] // 3
    disp = np.linalg.norm(basis.T.reshape(basis.shape[1], n, 3), axis=2)
    return [np.where(d > threshold_mm)[0] for d in disp]


def quiet_activity(weights: np.ndarray, targets: np.ndarray, valid: np.ndarray, markers: Sequence[np.ndarray],
                   still_mm: float = 0.5) -> np.ndarray:
    """Per shape: mean weight on the frames where none of its markers is displaced more than ``still_mm``
    from the neutral (NaN when there is no such frame, or the shape moves no marker). A shape active
    there is explaining misfit, not the face (a phantom)."""
    disp = np.where(valid, np.linalg.norm(targets, axis=2), 0.0)
    out = np.full(weights.shape[1], np.nan)
    for j, idx in enumerate(markers):
        if not len(idx):
            continue
        still = (disp[:, idx] <= still_mm).all(axis=1)
        if still.any():
            out[j] = float(weights[still, j].mean())
    return out


def jump_share(weights: np.ndarray, jump: float = 0.1) -> tuple[float, np.ndarray]:
    """(share of frame steps where any weight jumps by more than ``jump``, per-shape share)."""
    d = np.abs(np.diff(np.asarray(weights), axis=0)) > jump
    return float(d.any(axis=1).mean()), d.mean(axis=0)


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation (NaN when either curve is constant)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.std() == 0 or b.std() == 0:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


def distance(targets: np.ndarray, neutral: np.ndarray, i: int, j: int) -> np.ndarray:
    """Per frame: distance (mm) between markers ``i`` and ``j`` in the head frame."""
    p = targets + neutral
    return np.linalg.norm(p[:, i] - p[:, j], axis=1)


def rise(targets: np.ndarray, i: int, axis: int = 1) -> np.ndarray:
    """Per frame: displacement of marker ``i`` along ``axis`` (default +y, up) from the neutral (mm)."""
    return targets[:, i, axis]


@dataclass(frozen=True)
class Signal:
    """A shape and the marker geometry that should follow it (by marker labels)."""

    shape: str
    kind: str  # "distance" (between two markers) or "rise" (mean +y of the markers)
    markers: tuple[str, ...]


def signal_curve(signal: Signal, labels: Sequence[str], targets: np.ndarray, neutral: np.ndarray,
                 one_sided: bool = True) -> np.ndarray:
    """The signal's change from the neutral (mm), clipped at the neutral when ``one_sided``: a weight is >= 0, so
    the geometry moving the other way (the corner pulled down by the jaw or a frown, the chin raised by a smile) is
    another shape's motion, not a negative weight of this one. A weight active while its geometry is at or past the
    neutral still counts against it."""
    idx = [list(labels).index(lab) for lab in signal.markers]
    if signal.kind == "distance":
        i, j = idx
        curve = distance(targets, neutral, i, j) - np.linalg.norm(neutral[i] - neutral[j])
    elif signal.kind == "rise":
        curve = np.mean([rise(targets, i) for i in idx], axis=0)
    else:
        raise ValueError(f"unknown signal kind {signal.kind!r} (distance or rise)")
    return np.maximum(curve, 0.0) if one_sided else curve


def signal_correlations(signals: Sequence[Signal], names: Sequence[str], weights: np.ndarray,
                        labels: Sequence[str], targets: np.ndarray, neutral: np.ndarray,
                        one_sided: bool = True) -> dict[str, float]:
    """Correlation of each signal's shape weight with its marker geometry (signals whose shape or
    markers are absent are left out); ``one_sided=False`` is the signed geometry of the first baseline (issue 35),
    which mixes the other shapes' opposite motion into the criterion."""
    out = {}
    for s in signals:
        if s.shape not in names or not set(s.markers) <= set(labels):
            continue
        out[f"{s.shape}~{s.kind}({','.join(s.markers)})"] = correlation(
            weights[:, list(names).index(s.shape)], signal_curve(s, labels, targets, neutral, one_sided))
    return out


def max_weight(weights: np.ndarray, names: Sequence[str], pattern: re.Pattern = GAZE) -> float:
    """Largest weight of any shape whose name matches ``pattern`` (eye gaze by default) over the take."""
    cols = [j for j, n in enumerate(names) if pattern.search(n)]
    return float(np.asarray(weights)[:, cols].max()) if cols else float("nan")


def partners(weights: np.ndarray, names: Sequence[str], shape: str, top: int = 2) -> list[tuple[str, float]]:
    """The ``top`` shapes whose weight curves correlate most (by |r|) with ``shape``'s: a phantom that rises and
    falls with another shape is making up for that shape's misfit on this actor (issue 35: mouthFrown with the
    jaw shapes), not acting on its own."""
    W = np.asarray(weights, float)
    j = list(names).index(shape)
    r = [(names[k], correlation(W[:, j], W[:, k])) for k in range(W.shape[1]) if k != j]
    r = [(n, c) for n, c in r if np.isfinite(c)]
    return sorted(r, key=lambda nc: -abs(nc[1]))[:top]


def marker_residual(weights: np.ndarray, basis: np.ndarray, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per marker: RMS (mm, over the frames it is seen) of what the solve leaves unexplained, the stabilised
    displacement minus the basis times the weights: where the rig does not follow this actor's face."""
    T, n = np.shape(valid)
    r = np.asarray(targets, float).reshape(T, n, 3) - (np.asarray(weights) @ np.asarray(basis).T).reshape(T, n, 3)
    sq = np.where(valid, np.sum(r**2, axis=2), 0.0)
    return np.sqrt(sq.sum(axis=0) / np.maximum(np.count_nonzero(valid, axis=0), 1))
