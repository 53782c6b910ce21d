"""Synthetic facial performances with ground truth, for any rig and marker layout.

Weight curves are built from named events that look like acting (blinks, speech-like jaw and
lip motion, smiles, brow raises, idle twitches; a few poses beyond the rig's limits); shapes
are found by name, so ARKit-style rigs (``eyeBlinkLeft``) and ICT-style rigs (``eyeBlink_L``)
both work. The actor's face differs from the rig by a smooth non-affine warp; the head moves
rigidly; markers get Gaussian noise and occlusion bursts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.core.take import Take


@dataclass
class PerformanceSettings:
    seconds: float = 20.0
    rate: float = 120.0
    noise_mm: float = 0.5
    occlusion: float = 0.02  # fraction of marker-frames missing, in bursts
    head_degrees: float = 20.0
    head_mm: float = 30.0
    neutral_start: float = 1.0  # seconds of neutral face at the start (calibration span)
    neutral_end: float = 0.5
    beyond_limits: bool = True
    stable_dropout: float = 1.2  # seconds one stable marker is missing (0: never)
    seed: int = 1  # the performance (curves, head motion, noise)
    actor_seed: int = 7  # the actor's proportions: same actor_seed, same face


@dataclass
class Performance:
    take: Take
    weights: np.ndarray  # T x m ground truth
    names: list[str]
    head_rotation: np.ndarray  # T x 4 quaternion (x, y, z, w): raw = R @ head_frame + t
    head_translation: np.ndarray  # T x 3 mm
    actor_neutral: np.ndarray  # n x 3 actor markers at rest, head frame, mm
    settings: PerformanceSettings = field(default_factory=PerformanceSettings)

    def save_truth(self, path) -> None:
        np.savez_compressed(
            path, weights=self.weights.astype(np.float32), names=np.array(self.names),
            head_rotation=self.head_rotation, head_translation=self.head_translation,
            actor_neutral=self.actor_neutral, labels=np.array(self.take.labels), rate=self.take.rate,
            noise_mm=self.settings.noise_mm, occlusion=self.settings.occlusion, seed=self.settings.seed,
        )


@dataclass
class GroundTruth:
    weights: np.ndarray
    names: list[str]
    head_rotation: np.ndarray
    head_translation: np.ndarray
    actor_neutral: np.ndarray
    labels: list[str]

    @classmethod
    def load(cls, path) -> GroundTruth:
        z = np.load(path, allow_pickle=False)
        return cls(z["weights"].astype(np.float64), [str(n) for n in z["names"]], z["head_rotation"],
                   z["head_translation"], z["actor_neutral"], [str(s) for s in z["labels"]])


def _side(name: str) -> str | None:
    low = name.lower()
    if low.endswith(("left", "_l")):
        return "L"
    if low.endswith(("right", "_r")):
        return "R"
    return None


def _find(names: list[str], *keys: str, side: str | None = None) -> list[int]:
    out = []
    for i, n in enumerate(names):
        low = n.lower()
        if any(k in low for k in keys) and (side is None or _side(n) == side):
            out.append(i)
    return out


def _bump(t: np.ndarray, start: float, dur: float) -> np.ndarray:
    """Raised-cosine event: 0 outside [start, start + dur], 1 at its middle."""
    u = (t - start) / dur
    return np.where((u > 0) & (u < 1), 0.5 - 0.5 * np.cos(2 * np.pi * np.clip(u, 0, 1)), 0.0)


def _plateau(t: np.ndarray, start: float, dur: float, ramp: float) -> np.ndarray:
    up = np.clip((t - start) / ramp, 0, 1)
    down = np.clip((start + dur - t) / ramp, 0, 1)
    e = np.minimum(up, down)
    return e * e * (3 - 2 * e)


def weight_curves(names: list[str], upper: np.ndarray, s: PerformanceSettings,
                  rng: np.random.Generator) -> np.ndarray:
    n_frames = int(round(s.seconds * s.rate))
    t = np.arange(n_frames) / s.rate
    m = len(names)
    W = np.zeros((n_frames, m))
    cap = upper.copy()
    active_from, active_to = s.neutral_start, s.seconds - s.neutral_end

    def events(rate_hz: float, lo: float, hi: float):
        tt = active_from + rng.uniform(0, 2.0 / max(rate_hz, 1e-6))
        while tt < active_to - lo:
            dur = rng.uniform(lo, hi)
            if tt + dur <= active_to:
                yield tt, dur
            tt += dur + rng.exponential(1.0 / rate_hz)

    # idle twitches on every shape
    for k in range(m):
        for st, dur in events(0.08, 0.4, 1.6):
            W[:, k] += rng.uniform(0.1, 0.5) * _bump(t, st, dur)
    # blinks (occasionally one eye)
    blink_l, blink_r = _find(names, "blink", side="L"), _find(names, "blink", side="R")
    for st, dur in events(0.3, 0.18, 0.3):
        amp = rng.uniform(0.85, 1.0)
        sides = [blink_l, blink_r] if rng.random() > 0.1 else [blink_l if rng.random() < 0.5 else blink_r]
        for idx in sides:
            W[:, idx] += amp * _bump(t, st, dur)[:, None]
    # speech: syllables at ~4.5 Hz drive the jaw and a random lip shape each
    jaw = _find(names, "jawopen")
    lips = _find(names, "funnel", "pucker", "close", "press", "lowerdown", "upperup", "roll", "stretch")
    for st, dur in events(0.25, 1.5, 3.5):
        tt = st
        while tt < st + dur:
            syl = rng.uniform(0.16, 0.28)
            b = _bump(t, tt, syl)
            W[:, jaw] += rng.uniform(0.1, 0.5) * b[:, None]
            if lips:
                W[:, rng.choice(lips)] += rng.uniform(0.2, 0.7) * b
            tt += syl
    # smiles with a little asymmetry, cheeks following
    smile_l, smile_r = _find(names, "smile", side="L"), _find(names, "smile", side="R")
    cheek_l, cheek_r = _find(names, "cheeksquint", side="L"), _find(names, "cheeksquint", side="R")
    for st, dur in events(0.12, 1.5, 4.0):
        e = _plateau(t, st, dur, 0.3)
        amp = rng.uniform(0.4, 0.9)
        for idx, cidx in ((smile_l, cheek_l), (smile_r, cheek_r)):
            a = amp * rng.uniform(0.85, 1.0)
            W[:, idx] += a * e[:, None]
            W[:, cidx] += 0.5 * a * e[:, None]
    # brow raises and frowns
    raise_ids = _find(names, "browinnerup", "browouterup")
    frown_ids = _find(names, "browdown")
    for st, dur in events(0.15, 0.6, 2.0):
        ids = raise_ids if rng.random() < 0.7 else frown_ids
        W[:, ids] += rng.uniform(0.4, 1.0) * _plateau(t, st, dur, 0.15)[:, None]
    # poses the rig cannot reach: the actor goes past the sculpted extreme
    if s.beyond_limits and active_to - active_from > 4:
        for idx in (jaw, smile_l + smile_r):
            if idx:
                st = rng.uniform(active_from + 1, active_to - 2)
                W[:, idx] += 1.15 * _plateau(t, st, 1.0, 0.2)[:, None]
                cap[idx] = upper[idx] * 1.15
    return np.clip(W, 0.0, cap)


def head_motion(n_frames: int, rate: float, degrees: float, mm: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Smooth rigid head motion: rotations up to ``degrees`` (yaw; less pitch/roll), ``mm`` shifts."""
    t = np.arange(n_frames) / rate

    def smooth(amp: float) -> np.ndarray:
        out = np.zeros(n_frames)
        for _ in range(3):
            out += np.sin(2 * np.pi * rng.uniform(0.05, 0.4) * t + rng.uniform(0, 2 * np.pi))
        return amp * out / 3.0 * np.clip(t / 0.5, 0, 1)

    ang = np.stack([smooth(degrees * 0.6), smooth(degrees), smooth(degrees * 0.4)], 1)
    rot = Rotation.from_euler("xyz", ang, degrees=True)
    offset = np.array([rng.uniform(-300, 300), rng.uniform(1500, 1750), rng.uniform(-300, 300)])
    trans = offset + np.stack([smooth(mm) for _ in range(3)], 1)
    return rot.as_quat(), trans


def actor_warp(rng: np.random.Generator):
    """A smooth, non-affine change of proportions (wider/narrower, longer/shorter face)."""
    scale = rng.uniform([1.03, 0.92, 0.97], [1.10, 0.98, 1.06])
    quad = rng.uniform(-1, 1, 3) * np.array([6e-4, 4e-4, 4e-4])

    def warp(p: np.ndarray) -> np.ndarray:
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        return np.stack([scale[0] * x + quad[0] * x * y,
                         scale[1] * y + quad[1] * x * x,
                         scale[2] * z + quad[2] * y * y], -1)

    return warp


def perform(rig: Rig, layout: MarkerLayout, settings: PerformanceSettings | None = None,
            weights: np.ndarray | None = None) -> Performance:
    """Generate a take of ``layout``'s markers on an actor performing ``weights`` (or generated ones)."""
    s = settings or PerformanceSettings()
    rng = np.random.default_rng(s.seed)
    W = weight_curves(rig.names, rig.upper, s, rng) if weights is None else np.asarray(weights, float)
    n_frames = len(W)
    sites = layout.marker_rig(rig).evaluate(W)  # T x n x 3
    warp = actor_warp(np.random.default_rng(s.actor_seed))
    actor = warp(sites)
    actor_neutral = warp(layout.marker_rig(rig).neutral)
    quat, trans = head_motion(n_frames, s.rate, s.head_degrees, s.head_mm, rng)
    R = Rotation.from_quat(quat).as_matrix()
    raw = np.einsum("tij,tnj->tni", R, actor) + trans[:, None, :]
    raw += rng.normal(0.0, s.noise_mm, raw.shape)
    valid = np.ones(raw.shape[:2], dtype=bool)
    n = layout.n_markers
    if s.occlusion > 0:
        budget = s.occlusion * valid.size
        while (~valid).sum() < budget:
            length = int(rng.integers(3, 40))
            start = int(rng.integers(0, max(1, n_frames - length)))
            valid[start:start + length, rng.integers(0, n)] = False
    stable = np.where(layout.stable)[0]
    if s.stable_dropout > 0 and len(stable) and n_frames > 4 * s.rate:
        start = int(n_frames * 0.4)
        valid[start:start + int(s.stable_dropout * s.rate), stable[0]] = False
    take = Take(list(layout.labels), raw, valid, s.rate)
    return Performance(take, W, list(rig.names), quat, trans, actor_neutral, s)
