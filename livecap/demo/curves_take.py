"""Marker takes driven by real Live Link Face curves, for any rig, with full ground truth.

Real acting is dense (about half the shapes active in a typical frame) where scripted events are
sparse, so accuracy is measured on real curves (issue 15). The actor's face differs from the rig
by a seeded smooth warp (``performance.actor_warp``, centred on the face); the head moves as the
CSV says when it holds head angles, otherwise as ``performance.head_motion`` generates; markers get
Gaussian noise and occlusion bursts. The ground truth holds the true actor basis and head pose, so
the per-frame bounded least-squares *oracle* (true basis, true pose) can be computed.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from livecap.core.markers import MarkerLayout
from livecap.core.names import arkit_to_rig  # noqa: F401 - imported from here too
from livecap.core.rig import Rig
from livecap.core.take import Take
from livecap.demo.performance import actor_warp, head_motion
from transport.arkit import ARKIT_NAMES
from transport.llf_csv import read_llf_csv


@dataclass(frozen=True)
class CurveTakeSettings:
    rate: float = 60.0  # the curves' timecode rate; they hold a row about every second frame
    start: float = 0.0  # seconds into the CSV
    seconds: float = 0.0  # length of the take (0: to the end)
    noise_mm: float = 0.5
    occlusion: float = 0.05  # fraction of marker-frames missing, in bursts of 50-650 ms
    head_degrees: float = 15.0  # generated head motion when the CSV has none
    head_mm: float = 20.0
    neutral_seconds: float = 2.0  # the separate neutral take
    stable_dropout: float = 1.0  # seconds one stable marker is missing mid-take (0: never)
    seed: int = 1  # head motion, noise, occlusion, neutral noise (realeval: take_seed per file)
    actor_seed: int = 7  # the actor's proportions


def take_seed(source: str | Path, base: int = 1, draw: int = 0) -> int:
    """The noise / occlusion / neutral draw of one file's take: a CRC-32 of the file's name (stable across runs and
    machines, unlike Python's salted ``hash``) mixed with ``base`` and ``draw`` by numpy's ``SeedSequence``. One
    seed for every file made the files of ``livecap realeval`` share one draw (issue 41, 2026-12-06)."""
    crc = zlib.crc32(Path(source).name.encode("utf-8"))
    return int(np.random.SeedSequence([crc, int(base), int(draw)]).generate_state(1)[0])


def _centred_warp(seed: int, centre: np.ndarray):
    warp = actor_warp(np.random.default_rng(seed))
    return lambda p: warp(p - centre) + centre


def _bursts(valid: np.ndarray, fraction: float, rate: float, rng: np.random.Generator) -> None:
    n_frames, n = valid.shape
    lo, hi = max(1, int(0.05 * rate)), max(2, int(0.65 * rate))
    budget = fraction * valid.size
    while (~valid).sum() < budget:
        length = int(rng.integers(lo, hi))
        start = int(rng.integers(0, max(1, n_frames - length)))
        valid[start:start + length, rng.integers(0, n)] = False


@dataclass
class CurveTake:
    take: Take
    neutral: Take
    weights: np.ndarray  # T x m true rig weights
    names: list[str]
    head_rotation: np.ndarray  # T x 4 (x, y, z, w): raw = R @ head_frame + t
    head_translation: np.ndarray  # T x 3 mm
    actor_neutral: np.ndarray  # n x 3 head frame mm
    actor_basis: np.ndarray  # m x n x 3 the actor's marker displacement per unit weight (linearised)
    source: str
    unmapped: list[str]  # rig shapes no ARKit curve drives (always 0)
    blinks: list[int]  # rig shapes the ARKit blinks drive

    def save_truth(self, path: str | Path) -> None:
        np.savez_compressed(
            path, weights=self.weights.astype(np.float32), names=np.array(self.names),
            head_rotation=self.head_rotation, head_translation=self.head_translation,
            actor_neutral=self.actor_neutral, actor_basis=self.actor_basis, labels=np.array(self.take.labels),
            rate=self.take.rate, source=self.source)


def curves_take(rig: Rig, layout: MarkerLayout, csv_path: str | Path, settings: CurveTakeSettings | None = None,
                mapping: dict | None = None) -> CurveTake:
    """A take of ``layout``'s markers on a new actor performing the curves of ``csv_path``."""
    s = settings or CurveTakeSettings()
    curves = read_llf_csv(csv_path)
    arkit, head = curves.resample(s.rate)
    i0 = int(round(s.start * s.rate))
    i1 = len(arkit) if s.seconds <= 0 else i0 + int(round(s.seconds * s.rate))
    if i0 >= len(arkit) - 2:
        raise ValueError(f"{csv_path}: start {s.start} s is past its end ({len(arkit) / s.rate:.1f} s)")
    arkit = arkit[i0:i1]
    head = None if head is None else head[i0:i1]
    A = arkit_to_rig(list(rig.names), mapping)
    W = np.clip(arkit @ A.T, rig.lower, rig.upper)
    unmapped = [n for n, row in zip(rig.names, A, strict=True) if not row.any()]
    rng = np.random.default_rng(s.seed)
    mrig = layout.marker_rig(rig)
    warp = _centred_warp(s.actor_seed, mrig.neutral.mean(0))
    actor_neutral = warp(mrig.neutral)
    actor_basis = np.stack([warp(mrig.neutral + d) - actor_neutral for d in mrig.deltas])
    quat, trans = head_motion(len(W), s.rate, s.head_degrees, s.head_mm, rng)
    if head is not None:
        quat = Rotation.from_euler("YXZ", head).as_quat()
    take = _markers(warp(mrig.evaluate(W)), quat, trans, s, layout, rng, s.occlusion, s.stable_dropout)
    n_neutral = max(2, int(round(s.neutral_seconds * s.rate)))
    nq, nt = head_motion(n_neutral, s.rate, s.head_degrees / 3, s.head_mm / 3, rng)
    neutral = _markers(np.repeat(actor_neutral[None], n_neutral, 0), nq, nt, s, layout, rng, 0.0, 0.0)
    blinks = sorted(set(np.flatnonzero(A[:, [ARKIT_NAMES.index("eyeBlinkLeft"),
                                             ARKIT_NAMES.index("eyeBlinkRight")]].any(1)).tolist()))
    return CurveTake(take, neutral, W, list(rig.names), quat, trans, actor_neutral, actor_basis,
                     Path(csv_path).name, unmapped, blinks)


def _markers(actor: np.ndarray, quat: np.ndarray, trans: np.ndarray, s: CurveTakeSettings, layout: MarkerLayout,
             rng: np.random.Generator, occlusion: float, stable_dropout: float) -> Take:
    R = Rotation.from_quat(quat).as_matrix()
    raw = np.einsum("tij,tnj->tni", R, actor) + trans[:, None, :]
    raw += rng.normal(0.0, s.noise_mm, raw.shape)
    valid = np.ones(raw.shape[:2], dtype=bool)
    if occlusion > 0:
        _bursts(valid, occlusion, s.rate, rng)
    stable = np.where(layout.stable)[0]
    if stable_dropout > 0 and len(stable) and len(valid) > 4 * s.rate:
        start = int(len(valid) * 0.4)
        valid[start:start + int(stable_dropout * s.rate), stable[0]] = False
    return Take(list(layout.labels), raw, valid, s.rate)

