"""Calibration: from a neutral take and a target rig to everything a solver needs (the Profile).

* Neutral: the actor's rest markers, a robust (median) estimate over the first frames after
  head motion is removed (Curio et al. 2006 §2.1).
* Proportions: a map from the rig's marker sites to the actor's markers (Seol et al. 2012
  §3.2), applied to every shape's sites to give the marker-space basis B in the actor's
  proportions.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from livecap.markers import MarkerLayout
from livecap.rig import Rig
from livecap.stabilise import HeadStabiliser, kabsch
from livecap.take import Take


class CalibrationError(ValueError):
    pass


@dataclass
class Profile:
    """Everything calibration produced; saved to one ``.npz`` so a session starts instantly."""

    labels: list[str]
    names: list[str]
    source_neutral: np.ndarray  # n x 3, actor rest markers in the stabilised (head) frame, mm
    stable: np.ndarray  # n bool
    basis: np.ndarray  # 3n x m, actor-space marker displacement per unit weight
    lower: np.ndarray
    upper: np.ndarray
    target_sites: np.ndarray  # n x 3 rig marker sites at rest (rig frame)
    settings: dict = field(default_factory=dict)

    @property
    def n_markers(self) -> int:
        return len(self.labels)

    def stabiliser(self) -> HeadStabiliser:
        return HeadStabiliser(self.source_neutral, self.stable)

    def save(self, path: str | Path) -> None:
        np.savez_compressed(
            path, labels=np.array(self.labels), names=np.array(self.names),
            source_neutral=self.source_neutral, stable=self.stable, basis=self.basis,
            lower=self.lower, upper=self.upper, target_sites=self.target_sites,
            settings=np.array(json.dumps(self.settings)),
        )

    @classmethod
    def load(cls, path: str | Path) -> Profile:
        try:
            z = np.load(path, allow_pickle=False)
            return cls([str(s) for s in z["labels"]], [str(s) for s in z["names"]], z["source_neutral"],
                       z["stable"], z["basis"], z["lower"], z["upper"], z["target_sites"],
                       json.loads(str(z["settings"])))
        except (OSError, KeyError, ValueError) as exc:
            raise CalibrationError(f"{path}: not a livecap profile ({exc})") from None


def estimate_neutral(take: Take, stable: np.ndarray, frames: int | None = None) -> np.ndarray:
    """Actor rest markers from the first ``frames`` frames (all when None).

    Each frame is rigidly aligned to a running reference on the stable markers, then the
    per-marker median is taken, so a blink or a dropout inside the span does not move it.
    """
    span = take.slice(0, frames) if frames else take
    pos, val = span.positions, span.valid
    counts = val.sum(0)
    if (counts == 0).any():
        missing = [lab for lab, c in zip(take.labels, counts, strict=True) if c == 0]
        raise CalibrationError(f"markers never seen in the neutral span: {missing[:8]}")
    first = int(np.argmax(val.sum(1)))
    ref = np.where(val[first][:, None], pos[first], np.median(np.where(val[..., None], pos, np.nan), 0))
    ref = np.nan_to_num(ref)
    for _ in range(2):
        local, _, _ = HeadStabiliser(ref, stable).stabilise(pos, val)
        ref = np.nanmedian(np.where(val[..., None], local, np.nan), axis=0)
    return ref


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale, rotation, translation with s R src + t ~ dst (Umeyama 1991)."""
    R, _ = kabsch(src, dst)
    cs, cd = src.mean(0), dst.mean(0)
    s = np.sum((dst - cd) * ((src - cs) @ R.T)) / np.sum((src - cs) ** 2)
    return float(s), R, cd - s * R @ cs


def calibrate(rig: Rig, layout: MarkerLayout, neutral: np.ndarray, settings: dict | None = None) -> Profile:
    """Profile for ``rig`` seen through ``layout`` on an actor whose rest markers are ``neutral``."""
    sites_rig = layout.marker_rig(rig)
    sites = sites_rig.neutral
    s, R, t = similarity(sites, neutral)
    deltas = sites_rig.deltas  # m x n x 3
    basis = (s * np.einsum("ij,mnj->nim", R, deltas)).reshape(-1, rig.n_shapes)
    return Profile(list(layout.labels), list(rig.names), np.asarray(neutral, float), layout.stable.copy(),
                   basis, rig.lower.copy(), rig.upper.copy(), sites,
                   {"warp": "similarity", "scale": s, **(settings or {})})
