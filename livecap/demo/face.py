"""A procedural head-shaped face rig with ARKit-style shapes and anatomical marker sites.

Deterministic from a seed: the seed varies the head's proportions and each shape's extent a
little, so tests can draw different but plausible rigs. Units: millimetres; +y up, +z out of
the face, +x towards the subject's left (ARKit "Left").
"""

from __future__ import annotations

import numpy as np

from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig

# Moves: (cx, cy, sx, sy, dx, dy, dz): a Gaussian patch at (cx, cy) on the front of the face
# displaced by (dx, dy, dz) mm at its centre. "L" shapes are mirrored into their "R" twins.
PAIRED: dict[str, list[tuple[float, ...]]] = {
    "eyeBlink": [(32, 25, 11, 4, 0, -9, 1.0), (32, 14, 11, 3, 0, 1.5, 0)],
    "eyeSquint": [(32, 13, 11, 4, 0, 3, 1), (32, 25, 11, 4, 0, -2, 0), (46, 18, 6, 6, 1, 1, 0)],
    "eyeWide": [(32, 25, 11, 4, 0, 3.5, 0), (32, 42, 14, 6, 0, 1, 0)],
    "browDown": [(24, 42, 13, 6, -2, -5, -1)],
    "browOuterUp": [(45, 43, 10, 7, 0, 6, 0)],
    "cheekSquint": [(42, 4, 12, 10, 0, 4, 2)],
    "noseSneer": [(12, -6, 6, 10, 1, 4, 1), (20, 6, 6, 8, 0, 3, 0)],
    "mouthSmile": [(25, -45, 8, 8, 7, 6, -2), (38, -30, 12, 12, 2, 3, 2)],
    "mouthFrown": [(25, -45, 8, 8, 1, -6, 0), (30, -58, 10, 8, 0, -2, 0)],
    "mouthDimple": [(27, -45, 6, 6, 4, 0, -3)],
    "mouthStretch": [(25, -47, 8, 8, 5, -3, -1), (30, -65, 12, 10, 0, -2, 0)],
    "mouthPress": [(12, -40, 8, 4, 0, -1.5, -0.5), (12, -50, 8, 4, 0, 1.5, -0.5)],
    "mouthLowerDown": [(12, -53, 9, 5, 0, -5, 1)],
    "mouthUpperUp": [(12, -37, 9, 5, 0, 5, 1)],
}
CENTRAL: dict[str, list[tuple[float, ...]]] = {
    "browInnerUp": [(14, 43, 9, 6, 0, 6, 0.5), (-14, 43, 9, 6, 0, 6, 0.5)],
    "cheekPuff": [(45, -25, 15, 15, 6, 0, 4), (-45, -25, 15, 15, -6, 0, 4)],
    "mouthClose": [(0, -51, 20, 6, 0, 8, 0), (0, -38, 20, 5, 0, -3, 0)],
    "mouthFunnel": [(0, -38, 16, 5, 0, 2, 6), (0, -52, 16, 5, 0, -2, 6)],
    "mouthPucker": [(25, -45, 6, 6, -6, 0, 5), (-25, -45, 6, 6, 6, 0, 5), (0, -45, 14, 8, 0, 0, 7)],
    "mouthLeft": [(0, -45, 24, 12, 8, 0.5, 0), (25, -45, 8, 8, 2, 1, -1)],
    "mouthRight": [(0, -45, 24, 12, -8, 0.5, 0), (-25, -45, 8, 8, -2, 1, -1)],
    "mouthRollLower": [(0, -52, 18, 4, 0, 2, -4)],
    "mouthRollUpper": [(0, -38, 18, 4, 0, -2, -4)],
    "mouthShrugLower": [(0, -60, 18, 10, 0, 4, 2)],
    "mouthShrugUpper": [(0, -38, 18, 5, 0, 3, 1)],
}
# Jaw shapes move everything below the mouth line (a smooth mask): jawOpen rotates about a
# hinge behind the mouth, the others slide by one vector.
JAW_HINGE, JAW_OPEN_ANGLE = np.array([0.0, -25.0, -40.0]), 0.2
JAW: dict[str, tuple[float, float, float]] = {
    "jawForward": (0, 0, 6), "jawLeft": (6, -1, 0), "jawRight": (-6, -1, 0),
}
INBETWEENS = {  # shape -> (weight, extra displacement at that weight as a move list)
    "eyeBlinkLeft": (0.5, [(32, 25, 11, 4, 0, -1.0, 1.5)]),
    "eyeBlinkRight": (0.5, [(-32, 25, 11, 4, 0, -1.0, 1.5)]),
    "jawOpen": (0.5, "jaw", (0, -1.0, 2.0)),
}
CORRECTIVES = {
    ("jawOpen", "mouthSmileLeft"): [(25, -45, 8, 8, -1, 2, 1)],
    ("jawOpen", "mouthSmileRight"): [(-25, -45, 8, 8, 1, 2, 1)],
    ("eyeBlinkLeft", "eyeSquintLeft"): [(32, 20, 11, 4, 0, 1.5, 0)],
    ("jawOpen", "mouthSmileLeft", "mouthSmileRight"): [(0, -45, 20, 6, 0, 1, 0.5)],
}
# Marker sites: (label, x, y, stable). Mirrored pairs are written once with "_L".
MARKERS: list[tuple[str, float, float, bool]] = [
    ("FH_C", 0, 78, True), ("FH_L", 30, 74, True), ("TMP_L", 66, 36, True), ("NB", 0, 24, True),
    ("BRW_C", 0, 40, False), ("BRW_IN_L", 14, 42, False), ("BRW_MID_L", 30, 46, False),
    ("BRW_OUT_L", 47, 42, False), ("BRW_UP_L", 30, 57, False),
    ("LID_UP_L", 32, 26, False), ("LID_UP_IN_L", 23, 24, False), ("LID_LO_L", 32, 13, False),
    ("EYE_OUT_L", 47, 19, False), ("UE_L", 30, 2, False),
    ("CHK_HI_L", 45, 3, False), ("CHK_MID_L", 40, -18, False), ("CHK_LO_L", 45, -40, False),
    ("CHK_OUT_L", 60, -15, False), ("NOSE_LO", 0, 6, False), ("NOSE_TIP", 0, -12, False),
    ("NOSTRIL_L", 13, -16, False), ("NLF_L", 22, -28, False), ("PHILTRUM", 0, -29, False),
    ("LIP_UP_C", 0, -38, False), ("LIP_UP_L", 12, -39, False), ("LIP_LO_C", 0, -52, False),
    ("LIP_LO_L", 12, -51, False), ("CORNER_L", 25, -45, False), ("MTH_LO_L", 20, -60, False),
    ("CHIN_UP", 0, -68, False), ("CHIN_C", 0, -85, False), ("CHIN_L", 18, -80, False),
    ("CHIN_SIDE_L", 30, -70, False), ("JAW_L", 58, -55, False), ("JAW_LO_L", 42, -76, False),
]


def _head(n_u: int, n_v: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Ellipsoidal head front with nose, brow ridge, eye sockets, lips, chin and cheekbones."""
    a, b, c = 75 * rng.uniform(0.97, 1.03), 115 * rng.uniform(0.97, 1.03), 95 * rng.uniform(0.97, 1.03)
    th = np.linspace(-1.75, 1.75, n_u)
    ph = np.linspace(-1.15, 1.3, n_v)
    T, P = np.meshgrid(th, ph)
    x = a * np.sin(T) * np.cos(P)
    y = b * np.sin(P)
    z = c * np.cos(T) * np.cos(P)
    x *= 1 - 0.28 * np.clip(-np.sin(P), 0, None) ** 2

    def g(cx, cy, sx, sy):
        return np.exp(-0.5 * (((x - cx) / sx) ** 2 + ((y - cy) / sy) ** 2)) * (z > 0)

    z += 20 * g(0, -2, 8, 16) + 7 * g(0, -14, 7, 6)
    z -= 8 * (g(32, 20, 14, 9) + g(-32, 20, 14, 9))
    z += 5 * (g(28, 38, 18, 5) + g(-28, 38, 18, 5))
    z += 6 * g(0, -45, 18, 8) + 6 * g(0, -85, 12, 10)
    z += 4 * (g(48, 0, 12, 12) + g(-48, 0, 12, 12))
    verts = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    idx = np.arange(n_u * n_v).reshape(n_v, n_u)
    q00, q01, q10, q11 = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    tris = np.concatenate([np.stack([q00, q01, q11], -1).reshape(-1, 3),
                           np.stack([q00, q11, q10], -1).reshape(-1, 3)])
    return verts, tris


def _moves_field(neutral: np.ndarray, moves, scale: np.ndarray) -> np.ndarray:
    x, y, z = neutral.T
    out = np.zeros_like(neutral)
    front = z > 0
    for cx, cy, sx, sy, dx, dy, dz in moves:
        w = np.exp(-0.5 * (((x - cx) / sx) ** 2 + ((y - cy) / sy) ** 2)) * front
        out += w[:, None] * (np.array([dx, dy, dz]) * scale)
    return out


def _jaw_mask(neutral: np.ndarray) -> np.ndarray:
    x, y, z = neutral.T
    below = np.clip((-42.0 - y) / 14.0, 0.0, 1.0)
    below = below * below * (3 - 2 * below)
    lateral = np.clip(1 - 0.5 * (x / 70.0) ** 2, 0.0, 1.0)
    return below * lateral * (z > -20)


def _mirror(moves):
    return [(-cx, cy, sx, sy, -dx, dy, dz) for cx, cy, sx, sy, dx, dy, dz in moves]


def demo_rig(seed: int = 0, resolution: tuple[int, int] = (64, 56)) -> tuple[Rig, MarkerLayout]:
    """The demo rig (>= 3000 vertices, 43 ARKit-named shapes, in-betweens, correctives) and its markers."""
    rng = np.random.default_rng(seed)
    neutral, tris = _head(*resolution, rng)

    def jitter() -> np.ndarray:
        return rng.uniform(0.85, 1.15, 3)

    fields: dict[str, np.ndarray] = {}
    for base, moves in PAIRED.items():
        s = jitter()
        fields[base + "Left"] = _moves_field(neutral, moves, s)
        fields[base + "Right"] = _moves_field(neutral, _mirror(moves), s)
    for name, moves in CENTRAL.items():
        fields[name] = _moves_field(neutral, moves, jitter())
    jaw = _jaw_mask(neutral)[:, None]
    for name, vec in JAW.items():
        fields[name] = jaw * (np.array(vec) * jitter())
    angle = JAW_OPEN_ANGLE * jitter()[0]
    cos, sin = np.cos(angle), np.sin(angle)
    rel = neutral - JAW_HINGE
    turn = np.stack([np.zeros(len(rel)), rel[:, 1] * (cos - 1) - rel[:, 2] * sin,
                     rel[:, 1] * sin + rel[:, 2] * (cos - 1)], 1)
    fields["jawOpen"] = jaw * turn
    names = sorted(fields)
    faces = {n: neutral + fields[n] for n in names}
    for name, spec in INBETWEENS.items():
        w = spec[0]
        extra = jaw * np.array(spec[2]) if spec[1] == "jaw" else _moves_field(neutral, spec[1], np.ones(3))
        faces[f"{name}@{w:g}"] = neutral + w * fields[name] + extra
    for members, moves in CORRECTIVES.items():
        faces["+".join(members)] = neutral + sum(fields[n] for n in members) + _moves_field(neutral, moves, np.ones(3))
    rig = Rig.from_whole_face(neutral, tris, faces)
    return rig, demo_layout(neutral)


def demo_layout(neutral: np.ndarray) -> MarkerLayout:
    labels, verts, stable = [], [], []
    front = np.where(neutral[:, 2] > 0)[0]
    for label, x, y, st in MARKERS:
        sides = [(label, x)] if not label.endswith("_L") else [(label, x), (label[:-2] + "_R", -x)]
        for lab, xx in sides:
            d = np.hypot(neutral[front, 0] - xx, neutral[front, 1] - y)
            v = int(front[np.argmin(d)])
            if v in verts:
                raise AssertionError(f"marker {lab} collides with another marker site")
            labels.append(lab)
            verts.append(v)
            stable.append(st)
    return MarkerLayout.from_vertices(labels, verts, stable, units="mm")
