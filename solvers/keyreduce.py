"""Key reduction: dense weight curves -> a few cubic Hermite keys per shape within a max error.

Lewis et al. 2014 §5.4: motion capture gives a key on every frame, too dense for an animator to
edit; curve simplification keeps a few keys whose interpolant stays close to the dense curve.
Each segment between two keys is the cubic Hermite curve glTF's CUBICSPLINE sampler evaluates
(glTF 2.0 spec, Appendix C): values at the keys are the dense values, the out-tangent of the left
key and the in-tangent of the right key (units per second, "broken" tangents) are fitted by least
squares to the samples inside. Keys are placed greedily, each segment reaching as far as a
doubling-then-bisection search finds it within the bound; a one-frame segment is exact, so the
bound always holds. Everything is per shape and independent.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np


@dataclass(frozen=True)
class KeySettings:
    """``max_error``: largest |interpolant - dense| allowed at any frame (weight units)."""

    max_error: float = 0.01


@dataclass
class Keys:
    """One shape's keys: frame indices (into the dense curve), values, in/out tangents per second."""

    frames: np.ndarray
    values: np.ndarray
    in_tangents: np.ndarray
    out_tangents: np.ndarray


def hermite_basis(s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cubic Hermite basis at s in [0, 1]: (value0, slope0, value1, slope1)."""
    s2, s3 = s * s, s * s * s
    return 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2


@lru_cache(maxsize=4096)
def _uniform_basis(n: int) -> tuple[np.ndarray, ...]:
    """Hermite basis at n evenly spaced samples of [0, 1] and its 2 x 2 Gram entries (inner samples)."""
    h00, h10, h01, h11 = hermite_basis(np.linspace(0.0, 1.0, n))
    a, b = h10[1:-1], h11[1:-1]
    return h00, h10, h01, h11, np.array([a @ a, a @ b, b @ b])


def _fit_segment(t: np.ndarray, y: np.ndarray, uniform: bool = False) -> tuple[float, float, float]:
    """Slopes (out of the left key, into the right key) and max error of one segment's fit."""
    dt = t[-1] - t[0]
    if len(t) <= 2:
        slope = (y[-1] - y[0]) / dt
        return slope, slope, 0.0
    if uniform:
        h00, h10, h01, h11, gram = _uniform_basis(len(t))
        aa, ab, bb = gram * dt * dt
    else:
        h00, h10, h01, h11 = hermite_basis((t - t[0]) / dt)
        aa, ab, bb = dt * dt * np.array([h10[1:-1] @ h10[1:-1], h10[1:-1] @ h11[1:-1], h11[1:-1] @ h11[1:-1]])
    base = h00 * y[0] + h01 * y[-1]
    a, b, r = dt * h10[1:-1], dt * h11[1:-1], y[1:-1] - base[1:-1]
    det = aa * bb - ab * ab  # 2 x 2 normal equations; singular only for one inner sample
    ar, br = a @ r, b @ r
    if det > 1e-12 * aa * bb:
        m0, m1 = (bb * ar - ab * br) / det, (aa * br - ab * ar) / det
    else:  # rank one: the least-norm slopes
        (m0, m1), *_ = np.linalg.lstsq(np.stack([a, b], axis=1), r, rcond=None)
    err = float(np.max(np.abs(base + dt * (h10 * m0 + h11 * m1) - y)))
    return float(m0), float(m1), err


def reduce_curve(times: np.ndarray, values: np.ndarray, settings: KeySettings | None = None) -> Keys:
    """Keys for one dense curve (``times`` in seconds, increasing)."""
    tol = (settings or KeySettings()).max_error
    t, y = np.asarray(times, dtype=np.float64), np.asarray(values, dtype=np.float64)
    n = len(y)
    if n == 0:
        raise ValueError("key reduction needs at least one frame")
    d = np.diff(t)
    uniform = bool(len(d)) and bool(np.all(np.abs(d - d[0]) <= 1e-9 * abs(d[0])))
    frames, outs, ins = [0], [], []
    a = 0
    while a < n - 1:
        best = a + 1
        fit = _fit_segment(t[a:best + 1], y[a:best + 1], uniform)
        step, bad = 2, None
        while best < n - 1:  # doubling: the first end that fails the bound
            b = min(a + step, n - 1)
            f = _fit_segment(t[a:b + 1], y[a:b + 1], uniform)
            if f[2] > tol:
                bad = b
                break
            best, fit = b, f
            step *= 2
        if bad is not None:  # bisection between the last good and the first bad end
            lo_end, hi_end = best, bad
            while hi_end - lo_end > 1:
                mid = (lo_end + hi_end) // 2
                f = _fit_segment(t[a:mid + 1], y[a:mid + 1], uniform)
                if f[2] <= tol:
                    lo_end, fit = mid, f
                else:
                    hi_end = mid
            best = lo_end
        outs.append(fit[0])
        ins.append(fit[1])
        frames.append(best)
        a = best
    frames_arr = np.array(frames)
    in_t = np.array([0.0] + ins) if n > 1 else np.zeros(1)
    out_t = np.array(outs + [0.0]) if n > 1 else np.zeros(1)
    if n > 1:
        in_t[0], out_t[-1] = outs[0], ins[-1]
    return Keys(frames_arr, y[frames_arr], in_t, out_t)


def reduce_curves(times: np.ndarray, weights: np.ndarray, settings: KeySettings | None = None) -> list[Keys]:
    """Keys for every column of ``weights`` (T x m)."""
    return [reduce_curve(times, weights[:, j], settings) for j in range(weights.shape[1])]


def evaluate_keys(keys: Keys, times: np.ndarray, at: np.ndarray | None = None) -> np.ndarray:
    """The keys' cubic Hermite interpolant at ``at`` (default: every time of the dense curve)."""
    t = np.asarray(times, dtype=np.float64)
    at = t if at is None else np.asarray(at, dtype=np.float64)
    kt = t[keys.frames]
    if len(kt) == 1:
        return np.full(len(at), keys.values[0])
    i = np.clip(np.searchsorted(kt, at, side="right") - 1, 0, len(kt) - 2)
    dt = kt[i + 1] - kt[i]
    s = np.clip((at - kt[i]) / dt, 0.0, 1.0)
    h00, h10, h01, h11 = hermite_basis(s)
    return (h00 * keys.values[i] + dt * h10 * keys.out_tangents[i]
            + h01 * keys.values[i + 1] + dt * h11 * keys.in_tangents[i + 1])


def slope_keys(keys: Keys, times: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Derivative (per second) of the keys' interpolant at ``at``, inside a segment."""
    t = np.asarray(times, dtype=np.float64)
    kt = t[keys.frames]
    if len(kt) == 1:
        return np.zeros(len(at))
    i = np.clip(np.searchsorted(kt, at, side="right") - 1, 0, len(kt) - 2)
    dt = kt[i + 1] - kt[i]
    s = np.clip((at - kt[i]) / dt, 0.0, 1.0)
    d00, d10, d01, d11 = 6 * s * s - 6 * s, 3 * s * s - 4 * s + 1, -6 * s * s + 6 * s, 3 * s * s - 2 * s
    return ((d00 * keys.values[i] + d01 * keys.values[i + 1]) / dt
            + d10 * keys.out_tangents[i] + d11 * keys.in_tangents[i + 1])


def shared_keys(keys: list[Keys], times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All shapes keyed at the union of their key frames, the same curves exactly.

    glTF animates a mesh's morph weights with one sampler, one key time for every target. A cubic
    Hermite segment split at an inner time is the same curve with value and slope there as the new
    key, so each shape's interpolant is unchanged. Returns (frames, values, in, out), values K x m.
    """
    frames = np.unique(np.concatenate([k.frames for k in keys]))
    t = np.asarray(times, dtype=np.float64)[frames]
    K, m = len(frames), len(keys)
    values, ins, outs = np.zeros((K, m)), np.zeros((K, m)), np.zeros((K, m))
    for j, k in enumerate(keys):
        values[:, j] = evaluate_keys(k, times, t)
        slope = slope_keys(k, times, t)
        ins[:, j], outs[:, j] = slope, slope
        own = np.searchsorted(frames, k.frames)
        ins[own, j], outs[own, j] = k.in_tangents, k.out_tangents
    return frames, values, ins, outs
