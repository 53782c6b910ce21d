"""Rig transfer: a full blendshape rig and its marker sites for a new face from its neutral mesh alone.

The pipeline of Xiang et al. 2008 (Fig. 2), built on deformation transfer (Sumner & Popović 2004):

1. pre-align the generic neutral to the new face (similarity ICP, :mod:`.align`), then bend it
   onto the new face with a smooth warp (thin-plate ICP, :mod:`.warp`: Xiang's "roughly globally
   aligned" premise made strong enough for 6 %-of-the-eye-width patches);
2. detect the generic's landmarks (its markers.json sites) on the new face (§3.1, :mod:`.landmarks`);
3. deform the generic into the shape of the new face (§3.2, :mod:`.deformable`); optionally
   detect the landmarks again from the deformed model and deform once more (§4);
4. transfer every sculpt (shapes, in-betweens, correctives) from the generic onto the deformed
   generic (§3.3, :mod:`.deformation_transfer`), then carry the displacements to the new face's
   own topology through the dense correspondence (:mod:`.correspondence`);
5. carry the markers over (same labels and stable flags).

The new rig keeps the new face's vertices, triangles and frame; all geometry is in millimetres.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig, RigError
from livecap.transfer.align import Similarity, prealign
from livecap.transfer.correspondence import Correspondence, dense_correspondence, place_markers
from livecap.transfer.deformable import DeformResult, Schedule, deform
from livecap.transfer.deformation_transfer import DeformationTransfer
from livecap.transfer.landmarks import LandmarkResult, detect_landmarks, eye_width
from livecap.transfer.surface import Surface
from livecap.transfer.warp import DEFAULT_LENGTHS, smooth_warp

__all__ = ["TransferOptions", "TransferResult", "transfer", "transfer_rig", "transfer_steps", "Schedule"]


@dataclass
class TransferOptions:
    """Settings of the transfer; defaults are the paper's where the paper gives one."""

    prealign: str = "similarity"  # "similarity", "rigid" or "none"
    # smooth-warp pre-alignment: smoothing length per iteration in eye widths, coarse to fine; () skips it
    warp: tuple[float, ...] = DEFAULT_LENGTHS
    # landmark patch radius r_d as a fraction of the eye width (Xiang §3.1: 0.06), or several, coarse to fine
    radius_fraction: float | tuple[float, ...] = 0.06
    eye_width: float | None = None  # mm on the generic; default from its eye-corner markers
    max_angle: float = 60.0  # normal-compatibility test (degrees)
    schedule: Schedule = field(default_factory=Schedule)
    refine_landmarks: bool = False  # Xiang §4: detect again on the deformed model, deform again
    falloff: tuple[float, float] = (0.25, 1.0)  # displacement fade on the new face, in eye widths


@dataclass
class TransferResult:
    rig: Rig
    layout: MarkerLayout
    alignment: Similarity  # generic -> new face
    eye_width: float  # mm, on the generic after alignment
    eye_width_source: str
    landmarks: LandmarkResult  # the last detection
    first_landmarks: LandmarkResult  # the first detection (before the §4 refinement)
    deformed: DeformResult  # the generic topology in the new face's shape
    correspondence: Correspondence
    marker_snap: np.ndarray  # mm from each projected marker site to its bound vertex
    seconds: dict[str, float]


def transfer_steps(generic_rig: Rig, generic_layout: MarkerLayout, options: TransferOptions | None = None) -> int:
    """How many progress steps :func:`transfer` reports (for a progress bar's total)."""
    opt = options or TransferOptions()
    passes = 2 if opt.refine_landmarks else 1
    n_sculpts = generic_rig.n_shapes + len(generic_rig.inbetweens) + len(generic_rig.correctives)
    return passes * (generic_layout.n_markers + opt.schedule.iterations) + n_sculpts + 2 + len(opt.warp)


def transfer(generic_rig: Rig, generic_layout: MarkerLayout, target_neutral_vertices: np.ndarray,
             target_triangles: np.ndarray, options: TransferOptions | None = None,
             progress: Callable[[int, int], None] | None = None) -> TransferResult:
    """Run the whole pipeline; see :func:`transfer_rig` for the short form."""
    opt = options or TransferOptions()
    target_v = np.asarray(target_neutral_vertices, dtype=np.float64)
    target_f = np.asarray(target_triangles, dtype=np.int64).reshape(-1, 3)
    if target_v.ndim != 2 or target_v.shape[1] != 3 or not np.isfinite(target_v).all():
        raise RigError("target neutral must be V x 3 finite vertices")
    if len(target_f) == 0 or target_f.min() < 0 or target_f.max() >= len(target_v):
        raise RigError("target triangles must index the target's vertices")
    generic_layout.check(generic_rig, "generic layout")
    sculpts = generic_rig.whole_face()
    n_lm, its = generic_layout.n_markers, opt.schedule.iterations
    passes = 2 if opt.refine_landmarks else 1
    total = transfer_steps(generic_rig, generic_layout, opt)
    state = {"done": 0}

    def tick(k: int = 1) -> None:
        state["done"] += k
        if progress is not None:
            progress(min(state["done"], total), total)

    def sub(offset: int) -> Callable[[int, int], None]:
        def f(done: int, _total: int) -> None:
            if progress is not None:
                progress(min(offset + done, total), total)
        return f

    seconds: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        seconds[name] = seconds.get(name, 0.0) + now - clock
        clock = now

    target = Surface(target_v, target_f)
    generic = Surface(generic_rig.neutral, generic_rig.triangles)
    sim = prealign(generic, target, opt.prealign, max_angle=opt.max_angle)
    aligned = Surface(sim.apply(generic_rig.neutral), generic_rig.triangles)
    if opt.eye_width is not None:
        w_eye, how = opt.eye_width * sim.scale, "given"
    else:
        w_eye, how = eye_width(generic_layout, generic_rig.neutral)
        w_eye *= sim.scale
    lap("prealign")
    tick()
    warped = aligned
    if len(opt.warp):
        warped = Surface(smooth_warp(aligned.vertices, generic_rig.triangles, target, w_eye, opt.warp, opt.max_angle,
                                     progress=sub(state["done"])).vertices, generic_rig.triangles)
        tick(len(opt.warp))
        lap("smooth warp")

    sampling = generic_layout.sampling_matrix(generic_rig.n_vertices)
    centres = generic_layout.vertices[np.arange(n_lm), np.argmax(generic_layout.barycentric, axis=1)]
    source, first, lm, deformed = warped, None, None, None
    for _ in range(passes):
        sites = sampling @ source.vertices
        lm = detect_landmarks(source, sites, centres, target, np.asarray(opt.radius_fraction) * w_eye, opt.max_angle,
                              progress=sub(state["done"]))
        tick(n_lm)
        first = first or lm
        lap("landmarks")
        ok = np.where(lm.compatible)[0]
        deformed = deform(warped.vertices, generic_rig.triangles, sampling[ok], lm.points[ok], target,
                          opt.schedule, opt.max_angle, progress=sub(state["done"]))
        tick(its)
        lap("deformable model")
        source = Surface(deformed.vertices, generic_rig.triangles)
    assert lm is not None and deformed is not None and first is not None

    names = list(sculpts)
    dt = DeformationTransfer(aligned.vertices, deformed.vertices, generic_rig.triangles)
    lap("transfer factorisation")
    corr = dense_correspondence(source, target, opt.falloff[0] * w_eye, opt.falloff[1] * w_eye, opt.max_angle)
    carry = corr.matrix(generic_rig.n_vertices)
    lap("dense correspondence")
    tick()
    faces: dict[str, np.ndarray] = {}
    for name in names:
        moved = dt.transfer(sim.apply(sculpts[name]))
        faces[name] = target_v + np.asarray(carry @ (moved - deformed.vertices))
        tick()
    lap("deformation transfer")
    limits = {n: (float(a), float(b)) for n, a, b in zip(generic_rig.names, generic_rig.lower, generic_rig.upper,
                                                          strict=True)}
    rig = Rig.from_whole_face(target_v, target_f, faces, limits)
    layout, snap = place_markers(generic_layout, source, target, opt.max_angle)
    lap("markers")
    return TransferResult(rig, layout, sim, w_eye, how, lm, first, deformed, corr, snap, seconds)


def transfer_rig(generic_rig: Rig, generic_layout: MarkerLayout, target_neutral_vertices: np.ndarray,
                 target_triangles: np.ndarray, options: TransferOptions | None = None,
                 progress: Callable[[int, int], None] | None = None) -> tuple[Rig, MarkerLayout]:
    """A rig for the new face (its vertices, triangles, frame; millimetres) and its marker layout.

    ``generic_rig`` / ``generic_layout``: the rig to copy and its markers (the landmarks).
    ``target_neutral_vertices`` (V x 3, mm) / ``target_triangles`` (F x 3): the new face's neutral.
    Every shape, in-between and corrective of the generic is transferred; weight limits are kept.
    """
    res = transfer(generic_rig, generic_layout, target_neutral_vertices, target_triangles, options, progress)
    return res.rig, res.layout
