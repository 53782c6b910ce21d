"""Live preview window: a sink for ``livecap run`` that never slows the solver.

``publish(result)`` only drops the newest SolveResult into a one-slot mailbox (replacing an
unseen older one, counted in ``dropped``) and returns; a separate, niced render process owns
the window and its OpenGL context and asks for the newest result whenever it has drawn the
last one, so a slow display costs frames, not solver time. Attach it like any sink::

    sink = WindowSink(rig, layout, profile)   # raises NoDisplay with a clear message when headless
    for result in results: sink.publish(result)
    sink.close()
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.process import BaseProcess
from types import SimpleNamespace

import numpy as np

from livecap.core.result import SolveResult
from viewer.errors import NoDisplay, ViewerUnavailable

log = logging.getLogger("viewer.window")

QUAD_VS = """
#version 330
in vec2 in_xy;
out vec2 uv;
void main() { uv = vec2((in_xy.x + 1.0) / 2.0, (1.0 - in_xy.y) / 2.0); gl_Position = vec4(in_xy, 0.0, 1.0); }
"""
QUAD_FS = """
#version 330
uniform sampler2D image;
in vec2 uv;
out vec4 f_color;
void main() { f_color = vec4(texture(image, uv).bgr, 1.0); }
"""

NO_DISPLAY = ("no display: the live window needs an X11 or Wayland display ({why}); render offscreen with "
              "'livecap replay TAKE --rig RIG --preview out.mp4', or run under xvfb-run for a virtual display")


def check_display() -> None:
    """Raise NoDisplay unless a window system looks reachable (X11/Wayland on Linux)."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise NoDisplay(NO_DISPLAY.format(why="DISPLAY and WAYLAND_DISPLAY are unset"))


class LatestSlot:
    """A mailbox of size one: ``put`` never blocks, a newer item replaces an unread one."""

    def __init__(self) -> None:
        self._item = None
        self._has = False
        self._cond = threading.Condition()
        self.dropped = 0

    def put(self, item) -> None:
        with self._cond:
            if self._has:
                self.dropped += 1
            self._item, self._has = item, True
            self._cond.notify()

    def wake(self) -> None:
        """Wake a waiting ``take`` without an item (shutdown)."""
        with self._cond:
            self._cond.notify_all()

    def take(self, timeout: float):
        """The newest item, or None after ``timeout`` seconds."""
        with self._cond:
            if not self._has:
                self._cond.wait(timeout)
            if not self._has:
                return None
            item, self._item, self._has = self._item, None, False
            return item


class GlfwPresenter:
    """A glfw window whose context the preview renders in; frames are blitted as a textured quad."""

    def __init__(self, size: tuple[int, int], title: str = "livecap") -> None:
        check_display()
        try:
            import glfw
        except ImportError as exc:
            raise ViewerUnavailable(f"the live window needs glfw ({exc}); pip install glfw") from None
        import moderngl

        self._glfw = glfw
        errors: list[str] = []
        glfw.set_error_callback(lambda code, text: errors.append(text.decode(errors="replace")
                                                                  if isinstance(text, bytes) else str(text)))
        if not glfw.init():
            why = errors[-1] if errors else "glfw could not connect to the window system"
            raise NoDisplay(NO_DISPLAY.format(why=why))
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 4)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
        self.window = glfw.create_window(size[0], size[1], title, None, None)
        if not self.window:
            glfw.terminate()
            raise ViewerUnavailable("glfw could not open an OpenGL 4.3 window (libgl1-mesa-dri provides one in "
                                    "software)")
        glfw.make_context_current(self.window)
        glfw.swap_interval(0)  # never wait for vsync: the solver's rate rules
        self.ctx = moderngl.create_context(require=430)
        self._prog = self.ctx.program(vertex_shader=QUAD_VS, fragment_shader=QUAD_FS)
        quad = np.array([-1, -1, 1, -1, -1, 1, 1, 1], dtype="f4")
        self._vao = self.ctx.vertex_array(self._prog, [(self.ctx.buffer(quad.tobytes()), "2f", "in_xy")])
        self._tex = None

    def show(self, image: np.ndarray) -> bool:
        """Put a BGR image on screen; False once the user closed the window."""
        glfw = self._glfw
        h, w = image.shape[:2]
        if self._tex is None or self._tex.size != (w, h):
            self._tex = self.ctx.texture((w, h), 3)
        self._tex.write(np.ascontiguousarray(image).tobytes())
        fw, fh = glfw.get_framebuffer_size(self.window)
        self.ctx.screen.use()
        self.ctx.viewport = (0, 0, fw, fh)
        self._tex.use(0)
        self._vao.render(mode=5)  # TRIANGLE_STRIP
        glfw.swap_buffers(self.window)
        return self.poll()

    def poll(self) -> bool:
        self._glfw.poll_events()
        return not self._glfw.window_should_close(self.window)

    def close(self) -> None:
        self._glfw.destroy_window(self.window)
        self._glfw.terminate()


def render_loop(conn, rig, layout, profile, presenter, size, title, samples, nice: int) -> None:
    """The window's side of the sink: open the surface, then draw each result it is sent.

    Protocol on ``conn`` (a multiprocessing Pipe end). In: ("result", SolveResult), ("profile",
    :func:`display_profile` summary), ("stop", None). Out: ("error", exc) if the window cannot open; ("ready", counts)
    after opening and after each drawn frame (the request for the next one); ("closed", counts)
    when the user closed the window; ("failed", (counts, text)); ("bye", counts) after "stop".
    counts = (frames shown, seconds spent drawing).
    """
    if nice and hasattr(os, "nice"):
        try:
            os.nice(nice)  # the solver's process gets the CPU first; llvmpipe threads started below inherit this
        except OSError:
            pass
    from viewer.preview import Preview

    out = None
    try:
        out = presenter(size, title)
        preview = Preview(rig, layout, None, size, ctx=out.ctx, samples=samples)
        if profile is not None:
            adopt_profile(preview, profile)
        # the rig's neutral on screen at once; also compiles every shader (~0.2 s on llvmpipe) before frames come
        neutral = SolveResult(0, 0.0, list(rig.names), np.zeros(rig.n_shapes), np.array([0.0, 0.0, 0.0, 1.0]),
                              np.zeros(3))
        out.show(preview.draw_result(neutral, f"{title} - waiting for frames"))
    except BaseException as exc:
        try:
            conn.send(("error", exc))
        except Exception:  # an exception that does not pickle: keep its text
            conn.send(("error", ViewerUnavailable(f"{type(exc).__name__}: {exc}")))
        if out is not None:
            out.close()
        conn.close()
        return
    shown, seconds = 0, 0.0
    conn.send(("ready", (shown, seconds)))
    try:
        while True:
            if not conn.poll(0.03):
                if not out.poll():
                    conn.send(("closed", (shown, seconds)))
                    return
                continue
            kind, item = conn.recv()
            if kind == "stop":
                conn.send(("bye", (shown, seconds)))
                return
            start = time.perf_counter()
            if kind == "profile":  # once per session: the actor's calibration arrived
                adopt_profile(preview, item)
                continue
            keep = out.show(preview.draw_result(item, title))
            shown, seconds = shown + 1, seconds + time.perf_counter() - start
            if not keep:
                conn.send(("closed", (shown, seconds)))
                return
            conn.send(("ready", (shown, seconds)))
    except (EOFError, BrokenPipeError):  # the sink's side is gone
        pass
    except Exception as exc:  # a drawing failure ends the window, never the session
        try:
            conn.send(("failed", ((shown, seconds), f"{type(exc).__name__}: {exc}")))
        except OSError:
            pass
    finally:
        out.close()
        conn.close()


def display_profile(profile):
    """What the window needs of a calibration Profile: labels, source_neutral, target_sites and the
    rig-to-actor similarity, computed here in the solver's process.

    The window process gets this instead of the Profile: unpickling a Profile, or fitting the
    similarity, imports the calibration and solver modules there, which stalled the window's first
    calibrated second by 1-1.5 s on the loaded development VM (measured).
    """
    if profile is None:
        return None
    from viewer.scene import Similarity

    neutral = np.asarray(profile.source_neutral, dtype=np.float64)
    sites = np.asarray(profile.target_sites, dtype=np.float64)
    return SimpleNamespace(labels=list(profile.labels), source_neutral=neutral, target_sites=sites,
                           head=Similarity.fit(sites, neutral))


def adopt_profile(preview, shown) -> None:
    """Give a Preview a calibration in place (what ``Preview(rig, layout, profile)`` sets up), from
    :func:`display_profile`'s summary; no new Renderer (llvmpipe would compile every shader again).
    tests/test_viewer_window.py checks it draws exactly like a Preview constructed with the profile.
    """
    if preview.layout is None or list(shown.labels) != list(preview.layout.labels):
        raise ValueError("profile and marker layout list different markers")
    preview.source_neutral, preview.rest_sites, preview.head = shown.source_neutral, shown.target_sites, shown.head


class WindowSink:
    """Sink with ``publish(result)`` / ``close()`` drawing SolveResults in a live window.

    The window lives in its own process (``isolate=True``, default; spawned, niced): drawing on
    llvmpipe holds the GIL and the CPU for tens of ms per frame, which a thread would take from
    the solver. ``publish`` only puts the result into a one-slot mailbox (a newer result replaces
    an unseen one, counted in ``dropped``); a feeder thread sends the newest result each time the
    window asks for one, so at most one frame is in flight and the window never lags behind.

    ``profile`` may be None at first and arrive later through :meth:`set_profile` (``livecap run``
    calibrating on the stream's first second); until then the face is drawn without the actor's
    markers. ``presenter`` builds the output surface where the drawing runs (default: a glfw
    window); it must offer ``ctx`` (a moderngl context, or None for an offscreen one), ``show(image)
    -> bool``, ``poll() -> bool`` and ``close()``. ``isolate=False`` draws in a thread instead
    (same protocol; for presenters that cannot be pickled, e.g. in tests).
    """

    def __init__(self, rig, layout=None, profile=None, size: tuple[int, int] = (640, 480), title: str = "livecap",
                 presenter: Callable | None = None, samples: int = 0, isolate: bool = True,
                 nice: int = 5) -> None:
        import multiprocessing

        if presenter is None:
            check_display()  # fail in the caller's thread, before anything starts
            presenter = GlfwPresenter
        self.size, self.published, self.shown, self.render_seconds = tuple(size), 0, 0, 0.0
        self.closed_by_user = False
        self.failure: str | None = None  # why drawing stopped, if it failed
        self._slot = LatestSlot()
        self._stop = threading.Event()
        self._profile_lock = threading.Lock()
        self._new_profile = None
        mp = multiprocessing.get_context("spawn")  # never fork a process that has threads and GL state
        self._conn, theirs = mp.Pipe()
        args = (theirs, rig, layout, display_profile(profile), presenter, self.size, title, samples,
                nice if isolate else 0)
        if isolate:
            self._worker = mp.Process(target=render_loop, args=args, name="livecap-window", daemon=True)
        else:
            self._worker = threading.Thread(target=render_loop, args=args, name="livecap-window", daemon=True)
        self._worker.start()
        if isolate:
            theirs.close()  # so that our recv sees EOF if the process dies
        try:
            kind, payload = self._conn.recv()
        except EOFError:
            self._worker.join(5)
            raise ViewerUnavailable(f"the live window process ended before opening a window "
                                    f"(exit code {getattr(self._worker, 'exitcode', None)})") from None
        if kind == "error":
            self._worker.join(5)
            raise payload
        self._feeder = threading.Thread(target=self._feed, name="livecap-window-feed", daemon=True)
        self._feeder.start()

    @property
    def dropped(self) -> int:
        """Results the window never drew (replaced by a newer one while it was busy)."""
        return self._slot.dropped

    def set_profile(self, profile) -> None:
        """The actor's calibration, once known: later frames show the source markers and residual lines."""
        with self._profile_lock:
            self._new_profile = display_profile(profile)

    def publish(self, result) -> None:
        """Never waits: the result replaces any the window has not taken yet."""
        if not self._stop.is_set():
            self.published += 1
            self._slot.put(result)

    def stats(self) -> dict:
        """Counters for the run report; after close, published = shown + dropped."""
        ms = self.render_seconds / self.shown * 1e3 if self.shown else 0.0
        out = {"published": self.published, "shown": self.shown, "dropped": self.dropped,
               "draw_ms_mean": round(ms, 2), "closed_by_user": self.closed_by_user}
        if self.failure:
            out["failure"] = self.failure
        return out

    def _count(self, counts) -> None:
        self.shown, self.render_seconds = counts

    def _feed(self) -> None:
        """Wait for the window to ask, then send it the newest result (and a new profile first)."""
        asked = True  # the constructor consumed the window's first "ready"
        try:
            while True:
                if asked:
                    asked = False
                    kind, payload = "ready", (self.shown, self.render_seconds)
                else:
                    kind, payload = self._conn.recv()
                if kind == "failed":
                    counts, self.failure = payload
                    self._count(counts)
                    log.warning("live window stopped: %s", self.failure)
                    return
                self._count(payload)
                if kind == "closed":
                    self.closed_by_user = True
                    return
                item = None
                while item is None and not self._stop.is_set():
                    item = self._slot.take(timeout=0.1)
                if item is None:
                    return
                with self._profile_lock:
                    profile, self._new_profile = self._new_profile, None
                if profile is not None:
                    self._conn.send(("profile", profile))
                self._conn.send(("result", item))
        except (EOFError, OSError):
            if not self._stop.is_set():
                self.failure = "the window process ended"
        finally:
            self._stop.set()  # from now on publish is a no-op

    def close(self) -> None:
        """Stop drawing, collect the final counters, end the window (process or thread)."""
        self._stop.set()
        self._slot.wake()
        self._feeder.join(timeout=5)
        if not self._feeder.is_alive():
            try:
                self._conn.send(("stop", None))
                while self._conn.poll(5):
                    kind, payload = self._conn.recv()
                    if kind in ("bye", "ready"):
                        self._count(payload)
                    if kind == "bye":
                        break
            except (EOFError, OSError):
                pass
        if self._slot.take(timeout=0) is not None:  # the newest result, never drawn
            self._slot.dropped += 1
        self._worker.join(timeout=5)
        if isinstance(self._worker, BaseProcess) and self._worker.is_alive():
            self._worker.terminate()  # a frozen display must not hang the session's exit
            self._worker.join(timeout=5)
        self._conn.close()
