"""Purely emotional and purely verbal key models posed on a rig, for the compositing demo.

Pyun et al. 2003 §2 start from hand-made emotional key models (happy, sad, surprised, afraid,
angry) and visemes; here they are posed from the rig's shapes, found by name as in
livecap.demo.performance, so ARKit-style and ICT-style rigs both work.
"""

from __future__ import annotations

import numpy as np

from livecap.core.rig import Rig
from livecap.demo.performance import _find

EMOTIONS: dict[str, dict[tuple[str, ...], float]] = {
    "happy": {("smile",): 0.9, ("cheeksquint",): 0.6, ("eyesquint",): 0.3},
    "sad": {("frown",): 0.8, ("browinnerup",): 0.9, ("shruglower",): 0.4},
    "surprised": {("browinnerup", "browouterup"): 1.0, ("eyewide",): 0.9, ("jawopen",): 0.25},
    "afraid": {("browinnerup",): 1.0, ("eyewide",): 1.0, ("stretch",): 0.7},
    "angry": {("browdown",): 1.0, ("sneer",): 0.7, ("eyesquint",): 0.5, ("press",): 0.4},
}
VISEMES: dict[str, dict[tuple[str, ...], float]] = {
    "AA": {("jawopen",): 0.7},
    "EE": {("stretch",): 0.6, ("jawopen",): 0.2},
    "OO": {("pucker",): 0.9, ("funnel",): 0.5},
    "OH": {("funnel",): 0.9, ("jawopen",): 0.35},
    "MBP": {("close",): 0.8, ("press",): 0.6},
    "FV": {("rolllower",): 0.7, ("upperup",): 0.4},
}


def pose(rig: Rig, recipe: dict[tuple[str, ...], float]) -> np.ndarray:
    """Rig weights for a recipe {name fragments: weight}; fragments the rig lacks are ignored."""
    w = np.zeros(rig.n_shapes)
    for keys, value in recipe.items():
        w[_find(rig.names, *keys)] = value
    return np.clip(w, rig.lower, rig.upper)


def key_models(rig: Rig) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(emotional, verbal) key meshes (V x 3 each), skipping any the rig cannot pose."""
    def build(table):
        out = {}
        for name, recipe in table.items():
            w = pose(rig, recipe)
            if w.any():
                out[name] = rig.evaluate(w)
        return out

    return build(EMOTIONS), build(VISEMES)
