"""REFERENCE for tests: a hand fit of the AnimFace capture's markers onto the ICT rig.

What a user does by hand (issue 35): pick a few markers whose anatomy is clear, pair each with
the ICT landmark (multi-PIE, ICT's markers.json) at the same anatomical point, fit a similarity
on those pairs, then run scaled closest-point iterations of all markers onto the surface and
take each marker's closest surface point. Written independently of livecap.transfer.bind.
"""

from __future__ import annotations

import numpy as np

from livecap.transfer.surface import Surface
from solvers.rigid import similarity

# AnimFace marker -> ICT landmark(s) at the same anatomical point (mean when two)
ANCHORS: dict[str, tuple[str, ...]] = {
    "NoseHead": ("M30_nose",),  # nose tip
    "NoseTop": ("M27_nose",),  # nasal bridge between the eyes
    "Eyebrow_Center": ("M21_brow", "M22_brow"),  # glabella, between the inner brow ends
    "Mouth_Up": ("M51_lip",),  # upper lip centre
    "Mouth_Down": ("M57_lip",),  # lower lip centre
    "Leye_Inside": ("M42_eye",),
    "Reye_Inside": ("M39_eye",),
    "Leye_Outside": ("M45_eye",),
    "Reye_Outside": ("M36_eye",),
}


def hand_fit(labels: list[str], neutral: np.ndarray, sites: dict[str, np.ndarray], vertices: np.ndarray,
             triangles: np.ndarray, iterations: int = 60) -> np.ndarray:
    """Each marker's surface point (rig frame, mm) after the anchor similarity and closest-point iterations."""
    surf = Surface(vertices, triangles)
    idx = [labels.index(k) for k in ANCHORS]
    dst = np.array([np.mean([sites[s] for s in v], axis=0) for v in ANCHORS.values()])
    s, R, t = similarity(neutral[idx], dst)
    for _ in range(iterations):
        p = s * neutral @ R.T + t
        _, tri, bary = surf.closest(p)
        s, R, t = similarity(neutral, surf.point(tri, bary))
    _, tri, bary = surf.closest(s * neutral @ R.T + t)
    return surf.point(tri, bary)
