"""Keys for LINEAR glTF samplers: the frames at which straight segments through the dense samples
stay within a bound of every shape's curve.

Cubic keys (solvers/keyreduce.py, Lewis §5.4) are fewer, but importers that drop CUBICSPLINE
tangents (Blender 3.4's glTF importer) play them up to 0.072 off on the demo take. Linear keys
need no tangents, so every glTF player interpolates them alike. Keys are shared by all shapes
(one sampler input), chosen greedily: each segment is made as long as the worst shape allows
(doubling, then bisection of its end), the error measured at every frame; a one-frame segment
is exact, so the bound always holds at the samples.
"""

from __future__ import annotations

import numpy as np


def _within(times: np.ndarray, W: np.ndarray, i: int, j: int, bound: float) -> bool:
    s = (times[i:j + 1] - times[i]) / (times[j] - times[i])
    line = W[i] + s[:, None] * (W[j] - W[i])
    return bool(np.max(np.abs(line - W[i:j + 1])) <= bound)


def linear_keys(times: np.ndarray, W: np.ndarray, max_error: float) -> np.ndarray:
    """Key frame indices (sorted, first and last included) for ``W`` (T x m) sampled at ``times``."""
    if not max_error > 0:
        raise ValueError(f"max_error must be > 0, not {max_error}")
    T = len(W)
    keys, i = [0], 0
    while i < T - 1:
        lo, hi, n = i + 1, None, 2
        while hi is None and lo < T - 1:
            j = min(i + n, T - 1)
            if _within(times, W, i, j, max_error):
                lo, n = j, 2 * n
            else:
                hi = j
        while hi is not None and hi - lo > 1:
            mid = (lo + hi) // 2
            if _within(times, W, i, mid, max_error):
                lo = mid
            else:
                hi = mid
        keys.append(lo)
        i = lo
    return np.array(keys)


def evaluate_linear(key_times: np.ndarray, values: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The keys played back at ``times`` (T x m), as a LINEAR glTF sampler does."""
    return np.stack([np.interp(times, key_times, values[:, j]) for j in range(values.shape[1])], axis=1)
