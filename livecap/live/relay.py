"""A live session whose source already yields weights (the iPhone's ARKit curves): no calibration
and no solve, the same loop, sinks, flushing, stats and signal handling as the marker pipeline.

Smoothing (``smooth``) uses the streamed filters of the marker path (solvers/filters.py) on the 52
incoming weights and the head rotation's four components: ``1e`` is the 1€ filter with the robust
mode's weight settings (causal; its lag is its time constant, 1 / (2 pi fc) with fc = 1 Hz + 30 x the
weight's speed: 9.5 frames at 60 Hz on a still weight, ~1 frame on a moving one); an integer N is the
fixed-lag quadratic smoother, exactly N frames late (the frame published is the one N packets back).
"""

from __future__ import annotations

import gc
import time
from collections import deque
from collections.abc import Iterable

import numpy as np

from livecap.core.headpose import NeutralPose, NeutralWindow
from livecap.core.result import SolveResult
from livecap.live.pipeline import Pipeline


def _never_calibrate(take):
    raise AssertionError("a weights source needs no calibration")


class WeightsPipeline(Pipeline):
    """:class:`Pipeline` for a source of :class:`SolveResult`: each one is published as it comes, or,
    with ``retarget`` (livecap.retarget: by name, mapping or expression transfer), as the target rig's weights.

    The source's head rotation is already relative to its neutral (the app zeroes it on the
    phone), so every sink sends it unchanged rather than relative to the stream's first frames."""

    def __init__(self, source: Iterable[SolveResult], sinks: list, retarget=None, smooth: str = "none",
                 **kwargs) -> None:
        super().__init__(source, sinks, calibrator=_never_calibrate, **kwargs)
        self._solver = self  # marks the session ready: run() publishes from the first frame
        self.solver_mode = "weights-in"
        self.retarget = retarget
        self._names = list(retarget.names) if retarget is not None else None
        self.smoother = weight_smoother(smooth, self.rate)
        lag = getattr(self.smoother, "lag", 0)
        self._held: deque[SolveResult] = deque(maxlen=lag + 1)
        for sink in self.sinks:
            neutral = getattr(sink, "neutral", None)
            if isinstance(neutral, NeutralWindow):
                neutral.fix(NeutralPose(np.eye(3), np.zeros(3)))

    def run(self) -> dict:
        """The loop with BLAS on this thread alone and the start-up's objects out of the garbage collector's
        way: a 52 x 52 product woke OpenBLAS's other threads per packet, and a full collection walked every
        object numpy, scipy and zmq had made (both were p99 spikes of packet -> weights, docs/iphone.md)."""
        from threadpoolctl import threadpool_limits

        gc.collect()
        gc.freeze()
        try:
            with threadpool_limits(limits=1, user_api="blas"):
                return super().run()
        finally:
            gc.unfreeze()

    def solve_frame(self, frame: SolveResult) -> SolveResult | None:
        if self.smoother is not None:
            frame = self._smooth(frame)
            if frame is None:
                return None
        if self.retarget is None:
            self._step_time = 0.0
            return frame
        t0 = time.perf_counter()
        w = np.array(self.retarget.step(frame.weights), dtype=float)  # a copy: sinks may encode later
        self._step_time = time.perf_counter() - t0
        self.timing["step"].add(self._step_time)
        frame.names, frame.weights = self._names, w  # the source made this result for this packet alone
        return frame

    def _smooth(self, frame: SolveResult) -> SolveResult | None:
        """The filtered weights and head rotation, on the frame they belong to (None until a lag fills)."""
        q = frame.head_rotation if frame.head_rotation[3] >= 0 else -frame.head_rotation  # one sign: no flips
        y = self.smoother.step(np.concatenate([frame.weights, q]))
        self._held.append(frame)
        if len(self._held) < self._held.maxlen:
            return None
        out = self._held[0]
        out.weights = np.clip(y[:-4], 0.0, 1.0)  # a quadratic through a step overshoots
        out.head_rotation = y[-4:] / np.linalg.norm(y[-4:])
        return out


def weight_smoother(kind: str, rate: float):
    """``none``: None; ``1e``: the 1€ filter with the robust mode's weight settings; N: fixed lag of N frames."""
    from solvers.filters import FixedLagSmoother, OneEuroFilter

    if kind in ("none", "", None):
        return None
    if kind == "1e":
        from livecap.modes.robust import RobustSettings

        s = RobustSettings()
        return OneEuroFilter(rate, s.min_cutoff, s.euro_beta, s.d_cutoff)
    try:
        lag = int(kind)
    except ValueError:
        raise ValueError(f"--smooth {kind!r}: give none, 1e or a lag in frames (e.g. 2)") from None
    if lag < 1:
        raise ValueError(f"--smooth {kind!r}: a fixed lag is at least 1 frame")
    return FixedLagSmoother(lag)
