"""Which marker of one naming scheme is the same anatomical point as a marker of another.

Used to score landmark detection against a face's own markers when the two layouts are named
differently (Xiang et al. 2008 §4 score against hand-picked landmarks the same way).

``DEMO_TO_MULTIPIE``: the demo rig's anatomical labels (livecap.demo.face.MARKERS; ``_L`` is
the subject's left, +x) to the 68-landmark multi-PIE numbering used by ICT's markers.json
(0-based: 17-21 the subject's right brow, 22-26 the left, 27-30 nose bridge to tip, 31-35
nostrils right to left, 36-41 the right eye, 42-47 the left, 48-59 the outer lip ring starting
at the right corner). Only points with the same anatomical definition are listed; forehead,
temples, eyelid midpoints, cheeks, philtrum and the jaw side have no multi-PIE counterpart.
"""

from __future__ import annotations

import numpy as np

DEMO_TO_MULTIPIE: dict[str, str] = {
    "NB": "M27_nose",
    "BRW_IN_L": "M22_brow", "BRW_IN_R": "M21_brow",
    "BRW_MID_L": "M24_brow", "BRW_MID_R": "M19_brow",
    "BRW_OUT_L": "M26_brow", "BRW_OUT_R": "M17_brow",
    "EYE_OUT_L": "M45_eye", "EYE_OUT_R": "M36_eye",
    "NOSE_TIP": "M30_nose",
    "NOSTRIL_L": "M35_nose", "NOSTRIL_R": "M31_nose",
    "LIP_UP_C": "M51_lip", "LIP_LO_C": "M57_lip",
    "LIP_LO_L": "M56_lip", "LIP_LO_R": "M58_lip",
    "CORNER_L": "M54_lip", "CORNER_R": "M48_lip",
    "CHIN_C": "M08_jaw", "CHIN_L": "M09_jaw", "CHIN_R": "M07_jaw",
}


def label_map(source_labels: list[str], reference_labels: list[str]) -> dict[str, str]:
    """Source label -> reference label: identical names, else the demo/multi-PIE table."""
    ref = set(reference_labels)
    same = {lab: lab for lab in source_labels if lab in ref}
    if same:
        return same
    pairs = dict(DEMO_TO_MULTIPIE)
    pairs.update({v: k for k, v in DEMO_TO_MULTIPIE.items()})
    return {lab: pairs[lab] for lab in source_labels if lab in pairs and pairs[lab] in ref}


def landmark_distances(labels: list[str], points: np.ndarray, reference_labels: list[str],
                       reference_points: np.ndarray) -> list[tuple[str, str, float]]:
    """(label, reference label, distance mm) for every landmark with a counterpart in the reference."""
    ref = dict(zip(reference_labels, np.asarray(reference_points), strict=True))
    pairs = label_map(list(labels), list(reference_labels))
    return [(lab, pairs[lab], float(np.linalg.norm(p - ref[pairs[lab]])))
            for lab, p in zip(labels, np.asarray(points), strict=True) if lab in pairs]
