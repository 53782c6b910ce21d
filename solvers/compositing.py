"""Compositing emotional and verbal key models (Pyun et al. 2003 §2 and appendix).

Hand-made purely emotional key models E_j and purely verbal ones P_k (visemes), all displaced
from one base mesh, are combined automatically into E_j x P_k. Each vertex gets an importance
alpha_i in [0, 1] (appendix): how much it serves speech rather than emotion.

* p1 / e1: the vertex's largest displacement over the verbal / emotional keys, normalised by
  the largest over all vertices;
* p2 / e2: propagated to neighbours: the max of the vertex's own value and those of vertices
  closer than Lp / Le (on the base mesh) whose value exceeds S1;
* alpha_i = p2 (1 - e2) if p2 < S2, else 1 - (1 - p2) e2 (Eq. 13), which pushes alpha to 0 or 1.

Combination (§2): where alpha_i >= 0.5 the verbal displacement is kept whole and only the part
of the emotional one perpendicular to it is added, scaled by (1 - alpha_i); elsewhere the roles
swap:  dC = dP + (1 - a) P_perp(dE)  or  dC = dE + a E_perp(dP).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass
class ImportanceSettings:
    """Pyun's control parameters; lengths in the mesh's units (mm here)."""

    s1: float = 0.5  # only values above S1 propagate
    s2: float = 0.5  # Eq. 13's switch
    lp: float = 10.0  # verbal propagation radius
    le: float = 10.0  # emotional propagation radius


def normalised_max_displacement(base: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """p1 / e1: max_j |v_i^j - v_i| / max_{j,k} |v_k^j - v_k| (appendix, first step)."""
    mags = np.linalg.norm(np.asarray(keys, dtype=np.float64) - base[None], axis=2).max(axis=0)
    top = mags.max()
    return mags / top if top > 0 else np.zeros_like(mags)


def propagate(base: np.ndarray, value: np.ndarray, radius: float, s1: float) -> np.ndarray:
    """p2 / e2: each vertex takes the largest value above S1 found within ``radius`` (second step)."""
    out = value.copy()
    src = np.where(value > s1)[0]
    if len(src) == 0 or radius <= 0:
        return out
    pairs = cKDTree(base).sparse_distance_matrix(cKDTree(base[src]), radius, output_type="ndarray")
    near = pairs[pairs["v"] < radius]
    np.maximum.at(out, near["i"], value[src][near["j"]])
    return out


def importance(base: np.ndarray, emotional: np.ndarray, verbal: np.ndarray,
               settings: ImportanceSettings | None = None) -> np.ndarray:
    """alpha_i for every vertex (appendix, Eq. 13). ``emotional``/``verbal``: K x V x 3 key meshes."""
    s = settings or ImportanceSettings()
    base = np.asarray(base, dtype=np.float64)
    p2 = propagate(base, normalised_max_displacement(base, verbal), s.lp, s.s1)
    e2 = propagate(base, normalised_max_displacement(base, emotional), s.le, s.s1)
    return np.where(p2 < s.s2, p2 * (1.0 - e2), 1.0 - (1.0 - p2) * e2)


def perpendicular(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-row component of ``a`` perpendicular to ``b`` (all of ``a`` where ``b`` is zero)."""
    bb = np.einsum("ij,ij->i", b, b)
    coef = np.divide(np.einsum("ij,ij->i", a, b), bb, out=np.zeros_like(bb), where=bb > 1e-24)
    return a - coef[:, None] * b


def composite(base: np.ndarray, emotional: np.ndarray, verbal: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """The combined key model C (V x 3) of one emotional and one verbal key model (§2)."""
    base = np.asarray(base, dtype=np.float64)
    dE = np.asarray(emotional, dtype=np.float64) - base
    dP = np.asarray(verbal, dtype=np.float64) - base
    a = np.asarray(alpha, dtype=np.float64)[:, None]
    verbal_led = dP + (1.0 - a) * perpendicular(dE, dP)
    emotion_led = dE + a * perpendicular(dP, dE)
    return base + np.where(a >= 0.5, verbal_led, emotion_led)


def composite_all(base: np.ndarray, emotional: dict[str, np.ndarray], verbal: dict[str, np.ndarray],
                  settings: ImportanceSettings | None = None) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Every emotional x verbal combination, named ``<emotion>_<viseme>``, and the importance."""
    if not emotional or not verbal:
        raise ValueError("need at least one emotional and one verbal key model")
    alpha = importance(base, np.array(list(emotional.values())), np.array(list(verbal.values())), settings)
    out = {f"{e}_{p}": composite(base, E, P, alpha) for e, E in emotional.items() for p, P in verbal.items()}
    return out, alpha
