"""The live-window sink: publish never waits for drawing, the newest result wins, frames are real renders.

The window system itself needs a display, so the surface here is an offscreen presenter (EGL)
standing in for the glfw window; the thread, mailbox and rendering are the real ones.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from livecap.result import SolveResult
from viewer.errors import create_context
from viewer.window import LatestSlot, WindowSink


class OffscreenPresenter:
    """Same interface as GlfwPresenter; keeps the frames instead of showing them, slowly."""

    instances: list = []

    def __init__(self, size, title, delay: float = 0.05) -> None:
        self.ctx = create_context()
        self.frames: list[np.ndarray] = []
        self.delay = delay
        self.closed = False
        OffscreenPresenter.instances.append(self)

    def show(self, image) -> bool:
        time.sleep(self.delay)  # a slow display: the solver must not feel it
        self.frames.append(image)
        return True

    def poll(self) -> bool:
        return True

    def close(self) -> None:
        self.closed = True


def _result(rig, i: int, layout) -> SolveResult:
    w = np.zeros(rig.n_shapes)
    w[rig.index("jawOpen")] = (i % 10) / 10
    return SolveResult(i, i / 120, rig.names, w, np.array([0, 0, 0, 1.0]), np.zeros(3), solve_time=1e-4)


def test_latest_slot_keeps_the_newest_and_counts_drops():
    slot = LatestSlot()
    for i in range(5):
        slot.put(i)
    assert slot.take(0.01) == 4 and slot.dropped == 4
    assert slot.take(0.01) is None
    got = []
    consumer = threading.Thread(target=lambda: got.append(slot.take(2.0)))
    consumer.start()
    slot.put("late")
    consumer.join()
    assert got == ["late"]


def test_window_sink_drops_frames_instead_of_slowing_the_solver(demo):
    rig, layout = demo
    OffscreenPresenter.instances.clear()
    sink = WindowSink(rig, layout, size=(160, 120), presenter=OffscreenPresenter, isolate=False)
    start = time.perf_counter()
    n = 300
    for i in range(n):
        sink.publish(_result(rig, i, layout))
    publish_seconds = time.perf_counter() - start
    time.sleep(0.3)
    sink.close()
    out = OffscreenPresenter.instances[0]
    assert out.closed
    # each drawn frame costs >= 50 ms, so drawing them all would take >= 15 s; publishing took far less
    assert publish_seconds < 0.25 * n * out.delay
    assert 1 <= sink.shown < n and sink.dropped >= n - sink.shown - 1
    assert len(out.frames) == sink.shown
    frame = out.frames[-1]
    assert frame.shape == (120, 160, 3) and frame.std() > 10  # a real render, not a blank surface
    sink.publish(_result(rig, 0, layout))  # after close: ignored, no error
