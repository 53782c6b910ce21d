"""Live preview window: a sink for ``livecap run`` that never slows the solver.

``publish(result)`` only drops the newest SolveResult into a one-slot mailbox (replacing an
unseen older one, counted in ``dropped``) and returns; a render thread owns the window and
its OpenGL context (GL contexts belong to one thread) and draws the latest result at its own
pace. Attach it like any sink::

    sink = WindowSink(rig, layout, profile)   # raises NoDisplay with a clear message when headless
    for result in results: sink.publish(result)
    sink.close()
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable

import numpy as np

from viewer.errors import NoDisplay, ViewerUnavailable

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

NO_DISPLAY = ("no display for the live preview window ({why}); render offscreen instead with "
              "'livecap replay TAKE --rig RIG --preview out.mp4', or run under an X/Wayland session "
              "(xvfb-run gives a virtual one)")


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
        if not glfw.init():
            raise NoDisplay(NO_DISPLAY.format(why="glfw could not connect to the window system"))
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


class WindowSink:
    """Sink with ``publish(result)`` / ``close()`` drawing SolveResults in a live window.

    ``presenter`` builds the output surface inside the render thread (default: a glfw window);
    it must offer ``ctx`` (a moderngl context, or None for an offscreen one), ``show(image) ->
    bool``, ``poll() -> bool`` and ``close()``.
    """

    def __init__(self, rig, layout=None, profile=None, size: tuple[int, int] = (640, 480), title: str = "livecap",
                 presenter: Callable | None = None, samples: int = 0) -> None:
        if presenter is None:
            check_display()  # fail in the caller's thread, before any thread starts
            presenter = GlfwPresenter
        self.size, self.shown, self.render_seconds = tuple(size), 0, 0.0
        self._slot = LatestSlot()
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self.closed_by_user = False
        args = (rig, layout, profile, presenter, title, samples)
        self._thread = threading.Thread(target=self._run, args=args, name="livecap-window", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            raise self._error

    @property
    def dropped(self) -> int:
        """Results replaced before the window drew them (the solver outran the preview)."""
        return self._slot.dropped

    def publish(self, result) -> None:
        if not self._stop.is_set():
            self._slot.put(result)

    def close(self) -> None:
        self._stop.set()
        self._slot.wake()
        self._thread.join(timeout=5)

    def _run(self, rig, layout, profile, presenter, title, samples) -> None:
        from viewer.preview import Preview

        try:
            out = presenter(self.size, title)
            preview = Preview(rig, layout, profile, self.size, ctx=out.ctx, samples=samples)
        except BaseException as exc:  # hand it to the constructor, which re-raises in the caller
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        try:
            while not self._stop.is_set():
                result = self._slot.take(timeout=0.03)
                if result is None:
                    if not out.poll():
                        break
                    continue
                start = time.perf_counter()
                image = preview.draw_result(result, title)
                keep = out.show(image)
                self.render_seconds += time.perf_counter() - start
                self.shown += 1
                if not keep:
                    break
        finally:
            self.closed_by_user = not self._stop.is_set()
            self._stop.set()
            out.close()
