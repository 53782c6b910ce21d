"""Takes with model mismatch and ground truth: the actor is *another rig* (issue 35 item 4).

Every other generated take moves markers sitting exactly on the solved rig's vertices with the
rig's own shapes. A real capture has none of that. Here the actor is a second rig (e.g. the
MakeHuman head's sculpted expressions) driven by real Live Link Face curves through a name mapping;
its markers sit on the actor's anatomy where the target rig's marker sites are on the target's: the
target bent onto the actor's face by the rig transfer's landmarks and deformable fit (Xiang 2008,
:mod:`livecap.transfer`), each site taken at the closest point of the actor's skin whose normal agrees
(never skin facing away, as the plain closest point gave at the lips, nose and lids), moved by a
placement error in the tangent plane and lifted off the skin along the outward normal (skin offset,
constant in the head frame); the head moves; white optical noise is then low-passed as a capture
pipeline does (zero-phase Butterworth); markers drop out in bursts. The layout the solver gets is
*not* the true one: it is bound to the target rig from the neutral take by
:func:`livecap.transfer.bind.bind_capture`, as a user would.

Truth is what the actor did, on the target rig's names: the ARKit curves the actor's weights determine
(the minimum-norm ARKit vector reproducing them through the mapping), through the target's name match.
A name the mapping gives the actor no shape for (eye gaze, jaw sideways, mouthRoll ... on the MakeHuman
head) is truly at rest, and two ARKit names sharing one actor shape (mouthSmileLeft/Right on a symmetric
corner puller) are performed as their mean. The driving curves themselves are kept as ``curves``.
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
from livecap.transfer.bind import BindResult, bind_capture
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
    seed: int = 1  # placement, skin offsets, head motion, noise, occlusion (realeval: curves_take.take_seed per file)


@dataclass
class MismatchTake:
    take: Take
    neutral: Take
    layout: MarkerLayout  # bound to the target rig by bind_capture (what a user gets)
    binding: BindResult
    weights: np.ndarray  # T x m truth: what the actor did, on the target rig's shapes (module docstring)
    names: list[str]
    actor_weights: np.ndarray  # T x k the actor rig's weights
    source: str
    blinks: list[int]  # target shapes the ARKit blinks drive
    curves: np.ndarray  # T x m the driving curves on the target's shapes (the truth before 2026-12-05)
    performed: np.ndarray  # m, the target shapes the actor can show (others are at rest in ``weights``)

    def save_truth(self, path: str | Path) -> None:
        np.savez_compressed(path, weights=self.weights.astype(np.float32), names=np.array(self.names),
                            labels=np.array(self.take.labels), rate=self.take.rate, source=self.source,
                            curves=self.curves.astype(np.float32), performed=self.performed)


def actor_layout(actor: Rig, target: Rig, target_layout: MarkerLayout) -> tuple[MarkerLayout, np.ndarray]:
    """The target layout's sites on the actor's anatomy, and the target's outward normal there (n x 3): the target
    bent onto the actor by the rig transfer (Xiang 2008 landmarks and deformable fit), each site taken at the
    closest normal-compatible point of the actor's skin. Slow (~30 s for ICT onto MakeHuman): compute once per pair."""
    from livecap.transfer import transfer

    fit = transfer(target, target_layout, actor.neutral, actor.triangles)
    bent = Surface(fit.deformed.vertices, target.triangles)
    S = target_layout.sampling_matrix(target.n_vertices)
    normals = S @ bent.normals
    _, tri, bary, _ = Surface(actor.neutral, actor.triangles).closest_compatible(S @ bent.vertices, normals)
    layout = MarkerLayout(list(target_layout.labels), actor.triangles[tri], bary, target_layout.stable.copy())
    return layout, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def actor_sites(actor: Rig, anatomy: tuple[MarkerLayout, np.ndarray], s: MismatchSettings,
                rng: np.random.Generator) -> tuple[MarkerLayout, np.ndarray]:
    """``anatomy`` (:func:`actor_layout`) with the placement error, and each marker's skin offset vector (n x 3,
    mm, outward). Points are projected with the target's normals: the plain closest point took skin facing away on
    the MakeHuman head (22 of ICT's 60 offsets pointed into the head: every lip site, 5 nose, 5 eye)."""
    sites, normal = anatomy
    surf = Surface(actor.neutral, actor.triangles)
    tangent = np.cross(normal, rng.normal(size=normal.shape))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    moved = sites.marker_rig(actor).neutral + tangent * rng.uniform(-s.placement_mm, s.placement_mm,
                                                                     (len(normal), 1))
    _, tri, bary, _ = surf.closest_compatible(moved, normal)
    skin = surf.normal_at(tri, bary)
    skin *= np.sign(np.sum(skin * normal, axis=1, keepdims=True) + 1e-12)  # outward, whatever the winding
    offset = skin * rng.uniform(*s.skin_offset_mm, (len(tri), 1))
    layout = MarkerLayout(list(sites.labels), actor.triangles[tri], bary, sites.stable.copy())
    return layout, offset


def performed_truth(arkit: np.ndarray, actor: Rig, target: Rig, actor_mapping: dict | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(actor weights, truth, curves, performed): the actor's weights (T x k) for the ARKit ``arkit`` (T x 52); what
    it did on the target's names (module docstring); the curves on the target's names; and which target shapes the
    actor can show at all (the mapping gives a shape to one of their ARKit names)."""
    M = arkit_to_rig(list(actor.names), actor_mapping)
    A = arkit_to_rig(list(target.names))
    W_actor = np.clip(arkit @ M.T, actor.lower, actor.upper)
    did = W_actor @ np.linalg.pinv(M).T  # the least ARKit vector the actor's weights show
    performed = (np.abs(A) @ (np.abs(M).sum(0) > 0)) > 0
    return (W_actor, np.clip(did @ A.T, target.lower, target.upper), np.clip(arkit @ A.T, target.lower, target.upper),
            performed)


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
                  actor_mapping: dict | None = None, settings: MismatchSettings | None = None,
                  anatomy: tuple[MarkerLayout, np.ndarray] | None = None) -> MismatchTake:
    """``actor`` performs the curves of ``csv_path`` (``actor_mapping``: ARKit -> actor shapes) in front of
    markers placed like ``target_layout``'s (``anatomy``: :func:`actor_layout`'s, computed when not given); the
    markers are then bound to ``target`` from the neutral take."""
    s = settings or MismatchSettings()
    rng = np.random.default_rng(s.seed)
    arkit, _ = read_llf_csv(csv_path).resample(s.rate)
    i0 = int(round(s.start * s.rate))
    i1 = len(arkit) if s.seconds <= 0 else i0 + int(round(s.seconds * s.rate))
    if i0 >= len(arkit) - 2:
        raise ValueError(f"{csv_path}: start {s.start} s is past its end ({len(arkit) / s.rate:.1f} s)")
    arkit = arkit[i0:i1]
    W_actor, W_target, curves, performed = performed_truth(arkit, actor, target, actor_mapping)
    A = arkit_to_rig(list(target.names))
    blinks = sorted(np.flatnonzero(A[:, [ARKIT_NAMES.index("eyeBlinkLeft"),
                                         ARKIT_NAMES.index("eyeBlinkRight")]].any(1)).tolist())
    layout, offset = actor_sites(actor, anatomy or actor_layout(actor, target, target_layout), s, rng)
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
                        Path(csv_path).name, blinks, curves, performed)
