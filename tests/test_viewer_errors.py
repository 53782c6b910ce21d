"""Clear errors when OpenGL/EGL or a display is missing."""

from __future__ import annotations

import moderngl
import pytest

from viewer.errors import ViewerUnavailable, create_context
from viewer.window import NoDisplay, WindowSink, check_display


def test_missing_egl_names_the_debian_packages(monkeypatch):
    def broken(**kwargs):
        raise Exception("libEGL.so.1: cannot open shared object file")

    monkeypatch.setattr(moderngl, "create_standalone_context", broken)
    with pytest.raises(ViewerUnavailable, match="libegl1 libgl1-mesa-dri") as info:
        create_context()
    assert "libEGL.so.1" in str(info.value)
    assert isinstance(info.value, OSError)  # the CLI prints OSError as one line


def test_real_egl_context_failure_is_wrapped():
    with pytest.raises(ViewerUnavailable, match="libgl1-mesa-dri"):
        create_context(require=990)  # no driver offers GL 9.9: a real failure from the real stack


def test_no_display_is_a_clear_message(monkeypatch, demo):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    with pytest.raises(NoDisplay, match="--preview out.mp4"):
        check_display()
    rig, layout = demo
    with pytest.raises(NoDisplay, match="no display"):
        WindowSink(rig, layout)
