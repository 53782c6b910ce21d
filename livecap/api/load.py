"""Loading what a solve needs: a rig (every format ``livecap`` reads, dispatched in one place,
:func:`transport.rig_files.load_rig`), its marker layout, a take, a saved profile."""

from __future__ import annotations

from pathlib import Path

from livecap.api.errors import ApiError
from livecap.calibration.profile import Profile
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.core.take import Take


def _existing(parameter: str, path: str | Path) -> Path:
    p = Path(path)
    if not p.exists():
        raise ApiError(parameter, f"{p}: no such file or folder")
    return p


def load_rig(path: str | Path, *, mesh: str | None = None) -> Rig:
    """A rig from an OBJ folder, a .npz, glTF/GLB, VRM or USD (docs/rigs.md); ``mesh`` picks one mesh
    of a file that holds several."""
    from transport.rig_files import load_rig as load_rig_file

    return load_rig_file(_existing("path", path), mesh)


def load_layout(rig_path: str | Path, rig: Rig, *, markers: str | Path | None = None) -> MarkerLayout:
    """The rig's markers.json (``markers``, else the one in its OBJ folder or ``<rig>.markers.json``)."""
    from livecap.offline.setup import markers_path

    return MarkerLayout.load(_existing("markers", markers or markers_path(rig_path)), rig)


def load_take(path: str | Path) -> Take:
    """A marker take from .c3d, .trc or .csv (labels, positions in mm, valid mask, rate)."""
    from transport.takefile import read_take

    return read_take(_existing("path", path))


def load_profile(path: str | Path) -> Profile:
    """A profile ``livecap calibrate`` (or :meth:`Profile.save`) wrote."""
    return Profile.load(_existing("path", path))
