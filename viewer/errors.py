"""Clear errors when headless OpenGL is not available (what to install, not a traceback)."""

from __future__ import annotations

APT_HINT = ("install Mesa's EGL and software OpenGL: sudo apt-get install libegl1 libgl1-mesa-dri "
            "(Debian/Ubuntu; './dev' does it for you)")


class ViewerUnavailable(OSError):
    """OpenGL/EGL (or a display for the live window) cannot be used on this machine."""


class NoDisplay(ViewerUnavailable):
    """A live window was asked for but no display server is reachable."""


def gl_unavailable(exc: BaseException, backend: str = "egl") -> ViewerUnavailable:
    """Wrap whatever moderngl/glcontext raised when creating a context into one readable error."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return ViewerUnavailable(f"cannot create an OpenGL context through {backend.upper()} ({text}); {APT_HINT}")


def create_context(backend: str = "egl", require: int = 430):
    """A standalone (offscreen) moderngl context, or a ViewerUnavailable naming the Debian packages.

    ``require=430``: the deformation passes read storage buffers from the vertex shader (GL 4.3).
    """
    try:
        import moderngl
    except ImportError as exc:  # pragma: no cover - moderngl is a hard dependency
        raise ViewerUnavailable(f"moderngl is not installed ({exc}); pip install moderngl") from None
    try:
        ctx = moderngl.create_standalone_context(backend=backend, require=require)
    except Exception as exc:  # glcontext raises plain Exception for a missing libEGL/libGL
        raise gl_unavailable(exc, backend) from None
    return ctx
