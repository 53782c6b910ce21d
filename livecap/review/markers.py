"""Moving a bound marker on the review page (issue 35.1): the user drops a marker's site on the face
where the capture's marker really sits; the binding (rig triangle + barycentric) is kept in the session
and saved as markers.json for the next ``livecap calibrate``. The solve on the page is not redone: its
profile was calibrated with the old binding, so the page says to recalibrate."""

from __future__ import annotations

import numpy as np

from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.transfer.surface import barycentric


def rig_triangle(rig: Rig, corners: list[int]) -> np.ndarray:
    """The rig's triangle (its own vertex order) with these three corner vertices; ValueError if none."""
    want = np.sort(np.asarray(corners, dtype=np.int64))
    hit = np.flatnonzero((np.sort(rig.triangles, axis=1) == want).all(axis=1))
    if want.shape != (3,) or len(hit) == 0:
        raise ValueError(f"triangle: vertices {list(corners)} are not a triangle of the rig")
    return np.asarray(rig.triangles[hit[0]], dtype=np.int64)


def move_marker(layout: MarkerLayout, rig: Rig, label: str, corners: list[int], point: np.ndarray,
                rig_weights: np.ndarray) -> dict:
    """Bind ``label`` to the point of the rig triangle ``corners`` closest to ``point`` (mm), on the face as
    deformed by ``rig_weights`` (the frame the user dropped it on); the layout is changed in place."""
    tri = rig_triangle(rig, corners)
    at = MarkerLayout.from_vertices(["a", "b", "c"], tri, [False] * 3).marker_rig(rig).evaluate(rig_weights)
    bary = barycentric(np.asarray(point, dtype=float)[None], at, np.array([[0, 1, 2]]), np.array([0]))[0]
    i = layout.labels.index(label)
    trial = MarkerLayout(layout.labels, layout.vertices.copy(), layout.barycentric.copy(), layout.stable, layout.units)
    trial.vertices[i], trial.barycentric[i] = tri, bary
    if trial.coincident():
        raise ValueError(f"label: {label} would share its site with marker {trial.coincident()[0][0]}")
    layout.vertices[i], layout.barycentric[i] = tri, bary
    return {"label": label, "triangle": tri.tolist(), "barycentric": bary.tolist(),
            "site": (bary @ rig.neutral[tri]).tolist()}
