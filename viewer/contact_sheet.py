"""A contact sheet: the rig's neutral and its most pronounced shapes side by side, labelled.

How a user checks a rig at a glance (e.g. after ``livecap rig transfer``) without opening a DCC.
"""

from __future__ import annotations

import numpy as np

from livecap.core.rig import Rig
from viewer.compose import put_lines
from viewer.renderer import Renderer


def pronounced_shapes(rig: Rig, count: int) -> list[str]:
    """The ``count`` shapes that move the face most (max vertex displacement), strongest first."""
    reach = np.linalg.norm(rig.deltas, axis=2).max(axis=1)
    return [rig.names[k] for k in np.argsort(-reach)[:count]]


def contact_sheet(rig: Rig, names: list[str] | None = None, columns: int = 4,
                  tile: tuple[int, int] = (320, 320)) -> np.ndarray:
    """BGR image: neutral, then each shape in ``names`` at weight 1 (default: 7 most pronounced)."""
    names = pronounced_shapes(rig, 2 * columns - 1) if names is None else list(names)
    renderer = Renderer(rig, None, tile)
    tiles = []
    for name in [None, *names]:
        w = np.zeros(rig.n_shapes)
        if name is not None:
            w[rig.index(name)] = 1.0
        img = renderer.render(w, show_sites=False)
        put_lines(img, [name or "neutral"], bottom=False)
        tiles.append(img)
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)]
    return np.vstack(rows)
