"""A take solved exactly as ``livecap run`` solves a live stream, for accuracy figures (issue 41.4).

The take's frames go one at a time through :class:`livecap.live.pipeline.Pipeline` -- its causal head
stabiliser, its solver step, its latency alignment -- and a sink collects what it publishes. Offline
figures (``livecap solve``) smooth the head pose over a centred window and fill gaps from future
frames first; streamed figures must not, or they promise the live session what it cannot have.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from livecap.calibration.profile import Profile
from livecap.core.result import SolveResult
from livecap.core.take import Take
from livecap.live.pipeline import Pipeline


class _Collect:
    """A sink keeping each published frame's weights by frame number."""

    def __init__(self) -> None:
        self.weights: dict[int, np.ndarray] = {}

    def publish(self, result: SolveResult) -> None:
        self.weights[result.frame] = np.asarray(result.weights, dtype=float)

    def close(self) -> None:
        pass


@dataclass
class Streamed:
    weights: np.ndarray  # T x m, each frame's published weights (aligned by the mode's latency)
    mode: str  # the mode ``mode`` resolved to (auto: kalman or robust)
    seconds: float  # wall time of the whole run
    step_ms: dict[str, float]  # the mode's ``step`` alone: p50_ms, p99_ms, max_ms (the pipeline's own timing)


def stream_take(take: Take, profile: Profile, mode: str, options: dict | None = None) -> Streamed:
    """``take`` fed frame by frame to the live pipeline (which drains a lagged mode's last frames at the end). A
    frame it publishes nothing for (one the solver failed on) holds the previous published weights, as a live sink
    would."""
    sink = _Collect()
    pipe = Pipeline(take.select(profile.labels).frames(), [sink], profile=profile, rate=take.rate, mode=mode,
                    options=options)
    t0 = time.perf_counter()
    pipe.run()
    seconds = time.perf_counter() - t0
    W = np.zeros((take.n_frames, len(profile.names)))
    last = np.zeros(len(profile.names))
    for i in range(take.n_frames):
        last = sink.weights.get(take.first_frame + i, last)
        W[i] = last
    return Streamed(W, pipe.solver_mode or mode, seconds, pipe.timing["step"].percentiles())
