"""The live window on a real X server (Xvfb + Mesa llvmpipe through GLX), checked by screenshots.

Each test starts its own Xvfb on a free display (``-displayfd``), runs the window in a child
process with DISPLAY pointing there, and reads the screen back with ``xwd -root``: the pixels
are what the X server shows, so they prove the window is mapped and drawn, not only rendered.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

XVFB, XWD = shutil.which("Xvfb"), shutil.which("xwd")
pytestmark = pytest.mark.skipif(not (XVFB and XWD), reason="needs an X server to test the live window: "
                                "apt-get install xvfb x11-apps (./dev test installs them)")

W, H = 640, 480  # WindowSink's default size
SOURCE_RGB = (255, 209, 25)  # viewer.renderer.SOURCE_COLOUR: actor markers, drawn only once a profile is known


class Xvfb:
    """A private virtual X server; ``stop()``/``cont()`` freeze it like a display that hangs."""

    def __init__(self) -> None:
        r, w = os.pipe()
        self.proc = subprocess.Popen([XVFB, "-displayfd", str(w), "-screen", "0", "1280x720x24", "-nolisten", "tcp",
                                      "-br"], pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(w)
        text = b""
        deadline = time.monotonic() + 10
        while not text.endswith(b"\n") and time.monotonic() < deadline:
            if select.select([r], [], [], 0.2)[0]:
                chunk = os.read(r, 16)
                if not chunk:
                    break
                text += chunk
        os.close(r)
        if not text.strip().isdigit():
            self.close()
            pytest.fail(f"Xvfb did not report a display number (got {text!r})")
        self.display = f":{int(text)}"

    def env(self) -> dict:
        env = {k: v for k, v in os.environ.items() if k != "WAYLAND_DISPLAY"}
        env["DISPLAY"] = self.display
        return env

    def screenshot(self) -> np.ndarray:
        """The whole X screen as RGB uint8 (H, W, 3)."""
        raw = subprocess.run([XWD, "-root", "-silent", "-display", self.display], capture_output=True, check=True,
                             timeout=10).stdout
        return decode_xwd(raw)

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGSTOP)

    def cont(self) -> None:
        self.proc.send_signal(signal.SIGCONT)

    def close(self) -> None:
        self.cont()
        self.proc.terminate()
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def decode_xwd(raw: bytes) -> np.ndarray:
    """XWD (X Window Dump, ZPixmap, TrueColor) to RGB: header of CARD32s, colormap, then rows."""
    head = np.frombuffer(raw[:100], ">u4")
    header_size, fmt, width, height = int(head[0]), int(head[2]), int(head[4]), int(head[5])
    byte_order, bpp, bpl = int(head[7]), int(head[11]), int(head[12])
    masks, ncolors = [int(m) for m in head[14:17]], int(head[19])
    assert fmt == 2 and bpp in (24, 32), f"unexpected XWD layout: format {fmt}, {bpp} bits per pixel"
    start = header_size + 12 * ncolors
    rows = np.frombuffer(raw[start:start + bpl * height], np.uint8).reshape(height, bpl)
    k = bpp // 8
    px = rows[:, :width * k].reshape(height, width, k).astype(np.uint64)
    shifts = range(k) if byte_order == 0 else range(k - 1, -1, -1)  # LSBFirst / MSBFirst
    value = sum(px[..., i] << np.uint64(8 * s) for i, s in enumerate(shifts))
    out = []
    for m in masks:
        shift = (m & -m).bit_length() - 1
        out.append(((value & np.uint64(m)) >> np.uint64(shift)).astype(np.uint8))
    return np.stack(out, axis=-1)


@pytest.fixture
def xserver():
    server = Xvfb()
    yield server
    server.close()


@pytest.fixture(scope="module")
def take(tmp_path_factory) -> Path:
    """A short generated take (3 s at 120 Hz) with its rig and markers.json."""
    out = tmp_path_factory.mktemp("take")
    subprocess.run([sys.executable, "-m", "livecap", "generate", "--seconds", "3", "--out", str(out)], check=True,
                   capture_output=True, timeout=60)
    return out


def window_region(screen: np.ndarray) -> np.ndarray:
    """The window's pixels: the bounding box of everything not black (Xvfb -br: black root, no WM)."""
    ys, xs = np.nonzero(screen.max(axis=2) > 0)
    if len(ys) == 0:
        return screen[:0, :0]
    return screen[ys.min():ys.max() + 1, xs.min():xs.max() + 1]


def wait_for(server: Xvfb, check, timeout: float = 15.0) -> np.ndarray:
    """Screenshots until ``check(window)`` holds (the display is asynchronous); the last window."""
    deadline = time.monotonic() + timeout
    while True:
        win = window_region(server.screenshot())
        if check(win) or time.monotonic() > deadline:
            return win
        time.sleep(0.2)


def colour_pixels(img: np.ndarray, rgb, tol: int = 30) -> int:
    return int((np.abs(img.astype(int) - np.array(rgb)).max(axis=2) <= tol).sum())


CHILD = """
import sys, numpy as np
from livecap.core.rig import Rig
from livecap.core.markers import MarkerLayout
from livecap.core.result import SolveResult
from viewer.window import WindowSink
if __name__ == "__main__":
    rig = Rig.load(sys.argv[1]); layout = MarkerLayout.load(sys.argv[2], rig)
    w = np.zeros(rig.n_shapes); w[rig.index("jawOpen")] = 1.0; w[rig.index("browInnerUp")] = 0.7
    result = SolveResult(42, 0.35, rig.names, w, np.array([0.0, 0.17, 0.0, 0.985]), np.zeros(3), solve_time=0.0012)
    sink = WindowSink(rig, layout, title="x11 test")
    sink.publish(result)
    while sink.shown < 1:
        import time; time.sleep(0.02)
    print("shown", flush=True)
    sys.stdin.readline()
    sink.close()
    print(sink.stats(), flush=True)
"""


def test_window_shows_exactly_the_published_frame(xserver, take, tmp_path):
    """The screen holds the frame Preview renders offscreen for the same result (and not the neutral)."""
    from livecap.core.markers import MarkerLayout
    from livecap.core.result import SolveResult
    from livecap.core.rig import Rig
    from viewer.errors import create_context
    from viewer.preview import Preview

    rig_path, markers = take / "demo_rig.npz", take / "demo_rig.markers.json"
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(rig_path), str(markers)], env=xserver.env(),
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "shown", child.stderr.read()
        rig = Rig.load(rig_path)
        layout = MarkerLayout.load(markers, rig)
        preview = Preview(rig, layout, None, (W, H), ctx=create_context())
        w = np.zeros(rig.n_shapes)
        w[rig.index("jawOpen")], w[rig.index("browInnerUp")] = 1.0, 0.7
        result = SolveResult(42, 0.35, rig.names, w, np.array([0.0, 0.17, 0.0, 0.985]), np.zeros(3), solve_time=0.0012)
        expected = preview.draw_result(result, "x11 test")[..., ::-1].astype(int)  # BGR -> RGB
        neutral = preview.draw_result(SolveResult(42, 0.35, rig.names, np.zeros(rig.n_shapes),
                                                  np.array([0, 0, 0, 1.0]), np.zeros(3), solve_time=0.0012),
                                      "x11 test")[..., ::-1].astype(int)

        def matches(win):
            return win.shape == expected.shape and np.abs(win.astype(int) - expected).mean() < 1.0

        win = wait_for(xserver, matches)
        import cv2

        cv2.imwrite(str(tmp_path / "window.png"), win[..., ::-1])
        assert win.shape == (H, W, 3), f"window on screen is {win.shape[1]}x{win.shape[0]}, expected {W}x{H}"
        diff = np.abs(win.astype(int) - expected)
        assert diff.mean() < 1.0 and np.percentile(diff.max(axis=2), 99.9) <= 8, f"screen differs: {diff.mean()}"
        # the check can fail: the neutral face (what the window showed before the result) is far from it
        assert np.abs(win.astype(int) - neutral).mean() > 5 * max(diff.mean(), 0.2)
        child.stdin.write("\n")
        child.stdin.flush()
        out, err = child.communicate(timeout=20)
        assert child.returncode == 0, err
        assert "'shown': 1, 'dropped': 0" in out
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


def _run(take: Path, env: dict, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "livecap", "run", "--replay", str(take / "demo_take.c3d"), "--rig",
           str(take / "demo_rig.npz"), "--window", *extra]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _window_stats(report: str) -> dict:
    line = next(x for x in report.splitlines() if x.startswith("sink WindowSink"))
    pairs = (kv.strip().split(" ", 1) for kv in line.split(":", 2)[2].split(","))
    return {k: v for k, v in pairs}


def test_livecap_run_window_shows_the_calibrated_session(xserver, take, tmp_path):
    """``livecap run --window`` calibrating on the stream: the window ends up showing the actor's markers."""
    proc = _run(take, xserver.env(), "--loop")
    try:
        ready = proc.stdout.readline()
        assert ready.startswith("ready:") and "window 640x480" in ready, proc.stderr.read() if not ready else ready
        # yellow source markers appear only after calibration handed the profile to the window
        win = wait_for(xserver, lambda w: colour_pixels(w[:, 150:420], SOURCE_RGB) >= 20, timeout=20)
        import cv2

        cv2.imwrite(str(tmp_path / "run_window.png"), win[..., ::-1])
        assert win.shape == (H, W, 3)
        assert colour_pixels(win[:, 150:420], SOURCE_RGB) >= 20, "no source markers on screen after calibration"
        assert colour_pixels(win[:, 150:420], (38, 204, 255)) >= 20  # the rig's marker sites (cyan)
        skin = win[H // 2 - 20:H // 2 + 20, W // 2 - 20:W // 2 + 20].astype(int)
        # the lit face in the middle (skin albedo: red above blue), not the dark background
        assert skin.mean() > 80 and (skin[..., 0] > skin[..., 2]).mean() > 0.9
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    st = _window_stats(out)
    assert int(st["shown"]) >= 1 and st["closed_by_user"] == "False" and "failure" not in st
    assert int(st["published"]) == int(st["shown"]) + int(st["dropped"])


def test_a_frozen_display_never_slows_the_pipeline(xserver, take, tmp_path):
    """Freeze the X server (SIGSTOP) while ``livecap run --window`` plays the take at its own pace:
    every frame is still solved and published on time (counters), the window drops them instead."""
    stats = tmp_path / "stats.json"
    proc = _run(take, xserver.env(), "--end", "300", "--stats-file", str(stats), "--stats-every", "0.1")
    frozen = None
    try:
        ready = proc.stdout.readline()
        assert ready.startswith("ready:"), proc.stderr.read()
        xserver.stop()  # the window's next swap blocks until cont(): a display that hangs
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                st = json.loads(stats.read_text())
            except (OSError, ValueError):
                st = {}
            if st.get("frames_out", 0) >= 240:
                frozen = st
                break
            time.sleep(0.05)
    finally:
        xserver.cont()
        out, err = proc.communicate(timeout=30)
    assert frozen is not None, f"the pipeline stalled with the display frozen:\n{out}\n{err}"
    win = frozen["sinks"]["WindowSink:0"]
    # while frozen: nothing waits for the window; all but the frames it drew (at most the one in flight) dropped
    # (a mode with one frame of latency, kalman, holds the newest frame until the next arrives)
    assert 0 <= frozen["frames_in"] - frozen["frames_out"] <= 1 and frozen["pending_calibration"] == 0
    assert win["published"] == frozen["frames_out"]
    assert win["shown"] <= 1 and win["dropped"] >= frozen["frames_out"] - win["shown"] - 2
    assert not frozen["errors"]
    assert proc.returncode == 0, err
    final = _window_stats(out)
    assert "frames in 300, out 300" in out
    assert int(final["published"]) == 300 == int(final["shown"]) + int(final["dropped"])
