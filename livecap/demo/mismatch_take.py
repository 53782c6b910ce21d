"""Takes with model mismatch and ground truth: the actor is *another rig* (issue 35 item 4).

Every other generated take moves markers sitting exactly on the solved rig's vertices with the
rig's own shapes. A real capture has none of that. Here the actor is a second rig (e.g. the
MakeHuman head's sculpted expressions) driven by real Live Link Face curves through a name mapping;
its markers sit where the target rig's marker sites fall on the actor's face (similarity ICP onto
the actor's surface), moved by a placement error in the tangent plane and lifted off the skin
along the normal (skin offset, constant in the head frame); the head moves; white optical noise is
then low-passed as a capture pipeline does (zero-phase Butterworth); markers drop out in bursts.
The layout the solver gets is *not* the true one: it is bound to the target rig from the neutral
take by :func:`livecap.transfer.bind.bind_capture`, as a user would. Truth is the driving curves,
by the target rig's names.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.signal import butter, filtfilt

from livecap.core.markers import MarkerLayout
from livecap.core.names import arkit_to_rig
from livecap.core.rig import Rig
from livecap.core.take import Take
from livecap.demo.curves_take import _bursts
from livecap.demo.performance import head_motion
from livecap.transfer.bind import BindResult, _icp, _starts, bind_capture
from livecap.transfer.surface import Surface
from transport.arkit import ARKIT_NAMES
from transport.llf_csv import read_llf_csv


@dataclass(frozen=True)
class MismatchSettings:
    rate: float = 60.0
    start: float = 0.0  # seconds into the CSV
    seconds: float = 0.0  # 0: to the end
    skin_offset_mm: tuple[float, float] = (2.0, 5.0)  # markers this far off the actor's skin (uniform)
    placement_mm: float = 2.0  # marker placement error, uniform in the tangent plane (+-)
    noise_mm: float = 0.3  # raw optical noise before the pipeline's smoothing
    smoothing_hz: float = 6.0  # the capture pipeline's low-pass cut-off (0: none)
    occlusion: float = 0.02  # fraction of marker-frames missing, in bursts of 50-650 ms
    head_degrees: float = 6.0  # AnimFace: head motion up to ~6 degrees and 7-19 mm
    head_mm: float = 15.0
    neutral_seconds: float = 2.0
    seed: int = 1


@dataclass
class MismatchTake:
    take: Take
    neutral: Take
    layout: MarkerLayout  # bound to the target rig by bind_capture (what a user gets)
    binding: BindResult
    weights: np.ndarray  # T x m truth: the driving curves on the target rig's shapes
    names: list[str]
    actor_weights: np.ndarray  # T x k the actor rig's weights
    source: str
    blinks: list[int]  # target shapes the ARKit blinks drive

    def save_truth(self, path: str | Path) -> None:
        np.savez_compressed(path, weights=self.weights.astype(np.float32), names=np.array(self.names),
                            labels=np.array(self.take.labels), rate=self.take.rate, source=self.source)


def actor_sites(actor: Rig, target: Rig, target_layout: MarkerLayout, s: MismatchSettings,
                rng: np.random.Generator) -> tuple[MarkerLayout, np.ndarray]:
    """The target layout's sites placed on the actor's face (placement error included), and each
    marker's skin offset vector (n x 3, mm)."""
    sites = target_layout.sampling_matrix(target.n_vertices) @ target.neutral
    surf = Surface(actor.neutral, actor.triangles)
    best = min((_icp(sites, surf, start, 1.0) for start in _starts(sites, actor)), key=lambda r: r[1])[0]
    _, tri, bary = surf.closest(best.apply(sites))
    normal = surf.normal_at(tri, bary)
    tangent = np.cross(normal, rng.normal(size=normal.shape))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    moved = surf.point(tri, bary) + tangent * rng.uniform(-s.placement_mm, s.placement_mm, (len(tri), 1))
    _, tri, bary = surf.closest(moved)
    offset = surf.normal_at(tri, bary) * rng.uniform(*s.skin_offset_mm, (len(tri), 1))
    layout = MarkerLayout(list(target_layout.labels), actor.triangles[tri], bary, target_layout.stable.copy())
    return layout, offset


def _capture(markers: np.ndarray, s: MismatchSettings, rng: np.random.Generator,
             occlusion: float) -> tuple[np.ndarray, np.ndarray]:
    """``markers`` (T x n x 3, head frame) as captured: (positions, valid)."""
    from scipy.spatial.transform import Rotation

    quat, trans = head_motion(len(markers), s.rate, s.head_degrees, s.head_mm, rng)
    raw = np.einsum("tij,tnj->tni", Rotation.from_quat(quat).as_matrix(), markers) + trans[:, None, :]
    raw = raw + rng.normal(0.0, s.noise_mm, raw.shape)
    if s.smoothing_hz > 0 and len(raw) > 15:
        b, a = butter(2, s.smoothing_hz / (0.5 * s.rate))
        raw = filtfilt(b, a, raw, axis=0)
    valid = np.ones(raw.shape[:2], dtype=bool)
    if occlusion > 0:
        _bursts(valid, occlusion, s.rate, rng)
    return raw, valid


def mismatch_take(actor: Rig, target: Rig, target_layout: MarkerLayout, csv_path: str | Path,
                  actor_mapping: dict | None = None, settings: MismatchSettings | None = None) -> MismatchTake:
    """``actor`` performs the curves of ``csv_path`` (``actor_mapping``: ARKit -> actor shapes) in front of
    markers placed like ``target_layout``'s; the markers are then bound to ``target`` from the neutral take."""
    s = settings or MismatchSettings()
    rng = np.random.default_rng(s.seed)
    arkit, _ = read_llf_csv(csv_path).resample(s.rate)
    i0 = int(round(s.start * s.rate))
    i1 = len(arkit) if s.seconds <= 0 else i0 + int(round(s.seconds * s.rate))
    if i0 >= len(arkit) - 2:
        raise ValueError(f"{csv_path}: start {s.start} s is past its end ({len(arkit) / s.rate:.1f} s)")
    arkit = arkit[i0:i1]
    W_actor = np.clip(arkit @ arkit_to_rig(list(actor.names), actor_mapping).T, actor.lower, actor.upper)
    A = arkit_to_rig(list(target.names))
    W_target = np.clip(arkit @ A.T, target.lower, target.upper)
    blinks = sorted(np.flatnonzero(A[:, [ARKIT_NAMES.index("eyeBlinkLeft"),
                                         ARKIT_NAMES.index("eyeBlinkRight")]].any(1)).tolist())
    layout, offset = actor_sites(actor, target, target_layout, s, rng)
    mrig = layout.marker_rig(actor)
    labels = list(layout.labels)
    raw, valid = _capture(mrig.evaluate(W_actor) + offset, s, rng, s.occlusion)
    take = Take(labels, raw, valid, s.rate)
    n0 = max(2, int(round(s.neutral_seconds * s.rate)))
    nraw, nvalid = _capture(np.repeat((mrig.neutral + offset)[None], n0, 0), s, rng, 0.0)
    neutral = Take(labels, nraw, nvalid, s.rate)
    both = Take(labels, np.concatenate([nraw, raw]), np.concatenate([nvalid, valid]), s.rate)
    binding = bind_capture(both, target, None, span=(0, n0))  # stability measured over the performance
    return MismatchTake(take, neutral, binding.layout(target), binding, W_target, list(target.names), W_actor,
                        Path(csv_path).name, blinks)
