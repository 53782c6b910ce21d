"""A live session whose source already yields weights (the iPhone's ARKit curves): no calibration
and no solve, the same loop, sinks, flushing, stats and signal handling as the marker pipeline."""

from __future__ import annotations

import gc
import time
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

    def __init__(self, source: Iterable[SolveResult], sinks: list, retarget=None, **kwargs) -> None:
        super().__init__(source, sinks, calibrator=_never_calibrate, **kwargs)
        self._solver = self  # marks the session ready: run() publishes from the first frame
        self.solver_mode = "weights-in"
        self.retarget = retarget
        self._names = list(retarget.names) if retarget is not None else None
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

    def solve_frame(self, frame: SolveResult) -> SolveResult:
        if self.retarget is None:
            self._step_time = 0.0
            return frame
        t0 = time.perf_counter()
        w = np.array(self.retarget.step(frame.weights), dtype=float)  # a copy: sinks may encode later
        self._step_time = time.perf_counter() - t0
        self.timing["step"].add(self._step_time)
        frame.names, frame.weights = self._names, w  # the source made this result for this packet alone
        return frame
