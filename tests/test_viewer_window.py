"""The live-window sink: publish never waits for drawing, the newest result wins, frames are real renders.

The window system itself needs a display, so the surface here is an offscreen presenter (EGL)
standing in for the glfw window; the thread, mailbox and rendering are the real ones.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from livecap.core.result import SolveResult
from viewer.errors import create_context
from viewer.window import LatestSlot, WindowSink

REC = Path(__file__).resolve().parents[1] / "recordings"
HEADLESS = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}


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
    assert sink.published == n == sink.shown + sink.dropped  # every result is either drawn or counted
    assert len(out.frames) == sink.shown + 1  # + the neutral drawn while waiting for the first result
    frame = out.frames[-1]
    assert frame.shape == (120, 160, 3) and frame.std() > 10  # a real render, not a blank surface
    sink.publish(_result(rig, 0, layout))  # after close: ignored, no error
    assert sink.published == n


def _run(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "livecap", "run", "--replay", str(REC / "demo_take.c3d"), "--fast", *args]
    return subprocess.run(cmd, capture_output=True, text=True, env=env or HEADLESS, timeout=60)


def _dead_display() -> str:
    """A DISPLAY naming no X server: the window process itself finds out and says so."""
    n = next(n for n in range(97, 200) if not Path(f"/tmp/.X11-unix/X{n}").exists())
    return f":{n}"


@pytest.mark.parametrize("display", [None, "dead"])
def test_run_window_without_a_display_says_so_and_exits_2(display):
    env = dict(HEADLESS, DISPLAY=_dead_display()) if display else HEADLESS
    r = _run("--rig", str(REC / "demo_rig.npz"), "--window", env=env)
    assert r.returncode == 2 and "ready" not in r.stdout
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("livecap run: no display")
    assert "livecap replay" in lines[0] and "--preview" in lines[0] and "xvfb-run" in lines[0]


def test_run_window_optional_carries_on_without_a_display():
    r = _run("--rig", str(REC / "demo_rig.npz"), "--window-optional", "--max-frames", "130")
    assert r.returncode == 0, r.stderr
    assert "carrying on without the window" in r.stderr
    assert "frames in 130, out 130" in r.stdout and "WindowSink" not in r.stdout


def test_run_window_needs_the_rig():
    r = _run("--profile", "whatever.npz", "--window")
    assert r.returncode == 1 and "--window needs --rig" in r.stderr


def test_a_profile_adopted_later_draws_like_one_given_up_front():
    """set_profile's path (summary computed in the solver's process, adopted by the window's Preview)
    draws exactly what a Preview constructed with the profile draws: markers, residual lines, head."""
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from transport.takefile import read_take
    from viewer.preview import Preview
    from viewer.window import adopt_profile, display_profile

    rig = Rig.load(REC / "demo_rig.npz")
    layout = MarkerLayout.load(REC / "demo_rig.markers.json", rig)
    take = read_take(REC / "demo_take.c3d").select(layout.labels)
    profile = calibrate(rig, layout, estimate_neutral(take, layout.stable))
    ctx = create_context()
    markers = np.asarray(profile.source_neutral) + np.array([0.0, -3.0, 1.0])
    valid = np.ones(len(layout.labels), bool)
    valid[3] = False
    w = np.zeros(rig.n_shapes)
    w[rig.index("jawOpen")] = 0.6
    res = SolveResult(7, 0.05, rig.names, w, np.array([0.05, 0.1, 0.0, 0.99]), np.array([5.0, 0, 0]), 0.4, 1e-3,
                      markers, valid)
    direct = Preview(rig, layout, profile, (320, 240), ctx=ctx).draw_result(res, "t")
    later = Preview(rig, layout, None, (320, 240), ctx=ctx)
    without = later.draw_result(res, "t")
    adopt_profile(later, display_profile(profile))
    adopted = later.draw_result(res, "t")
    assert np.array_equal(adopted, direct)
    assert np.abs(without.astype(int) - direct).mean() > 0.5  # without the profile: no source markers, other pose
