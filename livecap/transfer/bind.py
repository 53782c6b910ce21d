"""Bind a real capture's markers to a rig: each marker on a triangle of the rig's surface.

A real optical capture puts markers on skin, 2-5 mm from any rig's surface, on an actor whose
proportions are not the rig's. From a near-neutral span of the take and the rig alone:

1. the span: the stillest ``window`` seconds within the take's first ``search`` seconds (or given);
2. the stable set, by rigidity over the take (or a range-of-motion take when given): markers whose
   distances to their most rigid partners vary least, white noise taken out; a marker's stability
   is its RMS deviation from the neutral in the head frame fitted on that set (Seol et al. 2012 §3.1);
3. a similarity of the markers onto the rig's surface. Start: when the rig's layout carries the
   multi-PIE landmarks (the rig transfer's landmarks, docs/transfer.md) and the capture's names
   match a common convention (``NAME_HINTS``), a similarity on those anchors; otherwise (names
   scrambled, or a rig without landmarks) several starts from the nose tips (the forward-most
   points; livecap's convention +y up, +z out of the face). Then a trimmed similarity ICP of the
   markers onto the surface (Besl & McKay; Umeyama 1991), as :mod:`.align` does for meshes;
4. each marker's closest surface point (triangle + barycentric) is its binding; its distance is
   the skin offset. Markers farther than ``max_distance`` or landing on the rig's open boundary
   (hair, a headband, off the rig's face) are reported and left unbound.

Xiang et al. 2008's deformable model (§3.2) is not run here: with 30-60 sparse skin markers
there is no target surface to deform onto, and the landmark term would need the anatomical
correspondences this step is meant to find.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.core.take import Take
from livecap.transfer.align import Similarity, _rotation, _umeyama
from livecap.transfer.surface import Surface
from solvers.rigid import kabsch


class BindError(ValueError):
    """A capture that cannot be bound; the message names the problem."""


# capture-name pattern (case-insensitive, full match) -> multi-PIE landmark of the rig's layout (ICT's numbering).
# Only midline points and symmetric pairs whose markers sit near the landmark in the usual conventions.
NAME_HINTS: dict[str, tuple[str, ...]] = {
    r"nose_?(head|tip)|nosetip": ("M30_nose",),
    r"nose_?(top|bridge)|nb": ("M27_nose",),
    r"eyebrow_?center|brow_?center|glabella": ("M21_brow", "M22_brow"),
    r"mouth_?up|upper_?lip|lip_?up(_c)?": ("M51_lip",),
    r"mouth_?down|lower_?lip|lip_?lo(_c)?": ("M57_lip",),
    r"l_?eye_?inside|lefteyeinner|eye_?in_?l": ("M42_eye",),
    r"r_?eye_?inside|righteyeinner|eye_?in_?r": ("M39_eye",),
    r"l_?eye_?outside|lefteyeouter|eye_?out_?l": ("M45_eye",),
    r"r_?eye_?outside|righteyeouter|eye_?out_?r": ("M36_eye",),
}


@dataclass(frozen=True)
class BindOptions:
    """Settings of :func:`bind_capture`; defaults measured on the AnimFace takes with ICT (docs/transfer.md)."""

    window: float = 0.5  # seconds of the auto-detected near-neutral span
    search: float = 1.5  # seconds: the span is searched at the take's start (captures start near neutral)
    trim: float = 1.0  # share of the nearest markers each ICP step fits (trimming lands in worse minima)
    max_distance: float = 8.0  # mm: farther from the surface after the fit, a marker is not on the rig's skin
    stable_ratio: float = 1.5  # stable: rigidity score within this factor of the most rigid marker's
    boundary_mm: float = 2.0  # mm: a marker this far beyond the rig's open boundary is off its face (hair, headband)
    rigid_floor_mm: float = 0.1  # rigidity scores below this count as this (noise-free takes: no 1.5 x 0)
    min_stable: int = 4  # at least this many stable markers (the most rigid ones) for head stabilisation
    use_names: bool = True  # start from NAME_HINTS anchors when the rig's layout has the landmarks


@dataclass
class MarkerBinding:
    label: str
    bound: bool
    triangle: int
    barycentric: np.ndarray
    distance: float  # mm, marker to its surface point after the fit (the skin offset)
    stability: float  # mm RMS deviation from the neutral in the head frame over the take
    stable: bool
    reason: str = ""  # why it is not bound


@dataclass
class BindResult:
    markers: list[MarkerBinding]
    alignment: Similarity  # capture (mm) -> rig frame
    span: tuple[int, int]  # frames of the neutral span
    anchors: list[tuple[str, str]]  # (capture label, rig landmark) pairs used for the start
    rms: float  # trimmed RMS marker-surface distance after the fit (mm)

    def layout(self, rig: Rig) -> MarkerLayout:
        """The bound markers as a layout on ``rig`` (triangle + barycentric)."""
        ok = [m for m in self.markers if m.bound]
        return MarkerLayout([m.label for m in ok], rig.triangles[[m.triangle for m in ok]],
                            np.array([m.barycentric for m in ok]), [m.stable for m in ok])


def neutral_span(take: Take, window: float = 0.5, search: float = 1.5) -> tuple[int, int]:
    """Frames (start, stop) of the stillest ``window`` seconds within the take's first ``search`` seconds."""
    n = max(2, int(round(window * take.rate)))
    if take.n_frames < n + 1:
        raise BindError(f"the take has {take.n_frames} frames, fewer than a {window} s neutral span")
    both = take.valid[1:] & take.valid[:-1]
    step = np.linalg.norm(np.diff(take.positions, axis=0), axis=2)
    speed = np.array([np.median(s[b]) if b.any() else np.inf for s, b in zip(step, both, strict=True)])
    last = max(1, min(int(search * take.rate) - n + 1, take.n_frames - n))
    csum = np.concatenate([[0.0], np.cumsum(speed)])
    cost = csum[n - 1:n - 1 + last] - csum[:last]
    start = int(np.argmin(cost))
    return start, start + n


def span_neutral(take: Take, span: tuple[int, int]) -> np.ndarray:
    """Mean position of every marker over the span (mm); a marker never seen there is an error."""
    pos, val = take.positions[span[0]:span[1]], take.valid[span[0]:span[1]]
    count = val.sum(axis=0)
    if (count == 0).any():
        missing = [lab for lab, c in zip(take.labels, count, strict=True) if c == 0]
        raise BindError(f"markers {missing[:5]} are missing throughout the neutral span (give another --span)")
    return (pos * val[..., None]).sum(axis=0) / count[:, None]


def stability(take: Take, neutral: np.ndarray, options: BindOptions = BindOptions()) -> tuple[np.ndarray, np.ndarray]:
    """(per-marker RMS deviation from the neutral in the head frame, stable mask).

    The stable set is chosen without a head frame first: a marker is rigid when its distances to
    its most rigid partners vary least over the take (no alignment to go wrong when half the
    markers move with the jaw). The head frame is then the rigid fit on that set.
    """
    pos, val = take.positions, take.valid
    n = take.n_markers
    # white marker noise inflates every spread alike and would hide rigidity: take it out, per marker, from
    # the second differences (var(p[t+1] - 2p[t] + p[t-1]) = 6 sigma^2 per axis for white noise)
    acc = np.diff(pos, 2, axis=0)
    seen = val[2:] & val[1:-1] & val[:-2]
    noise = np.array([np.mean(acc[seen[:, i], i] ** 2) / 6 if seen[:, i].any() else 0.0 for i in range(n)])
    spread = np.zeros((n, n))
    for i in range(n):
        d = np.linalg.norm(pos - pos[:, i:i + 1], axis=2)
        w = val & val[:, i:i + 1]
        cnt = np.maximum(w.sum(axis=0), 1)
        mean = (d * w).sum(axis=0) / cnt
        spread[i] = np.sqrt(np.maximum((((d - mean) ** 2) * w).sum(axis=0) / cnt - noise[i] - noise, 0.0))
    np.fill_diagonal(spread, np.inf)
    k = max(options.min_stable - 1, n // 4)
    score = np.sort(spread, axis=1)[:, :k].mean(axis=1)
    stable = score <= options.stable_ratio * max(score.min(), options.rigid_floor_mm)
    stable[np.argsort(score)[:options.min_stable]] = True
    w = val * stable
    R, t = kabsch(pos, np.broadcast_to(neutral, pos.shape), w)
    aligned = np.einsum("tij,tnj->tni", R, pos) + t[:, None, :]
    err = np.sum((aligned - neutral) ** 2, axis=2)
    dev = np.sqrt((err * val).sum(axis=0) / np.maximum(val.sum(axis=0), 1))
    return dev, stable


def _hint_anchors(labels: list[str], neutral: np.ndarray, layout: MarkerLayout | None, rig: Rig
                  ) -> tuple[list[tuple[str, str]], np.ndarray, np.ndarray]:
    if layout is None:
        return [], np.zeros((0, 3)), np.zeros((0, 3))
    sites = dict(zip(layout.labels, layout.sampling_matrix(rig.n_vertices) @ rig.neutral, strict=True))
    pairs, src, dst = [], [], []
    for pattern, targets in NAME_HINTS.items():
        if not all(t in sites for t in targets):
            continue
        hits = [i for i, lab in enumerate(labels) if re.fullmatch(pattern, lab, flags=re.IGNORECASE)]
        if len(hits) == 1:
            pairs.append((labels[hits[0]], "+".join(targets)))
            src.append(neutral[hits[0]])
            dst.append(np.mean([sites[t] for t in targets], axis=0))
    return pairs, np.array(src).reshape(-1, 3), np.array(dst).reshape(-1, 3)


def _icp(points: np.ndarray, surface: Surface, start: Similarity, trim: float, iterations: int = 300
         ) -> tuple[Similarity, float]:
    current, rms = start, np.inf
    for _ in range(iterations):
        p = current.apply(points)
        dist, tri, bary = surface.closest(p)
        keep = dist <= np.quantile(dist, trim)
        rms = float(np.sqrt(np.mean(dist[keep] ** 2)))
        step = _umeyama(p[keep], surface.point(tri[keep], bary[keep]), True)
        current = current.then(step)
        if abs(step.scale - 1) + np.linalg.norm(step.rotation - np.eye(3)) + np.linalg.norm(step.translation) < 1e-7:
            break
    return current, rms


def _starts(neutral: np.ndarray, rig: Rig) -> list[Similarity]:
    """Geometric starts: nose tips (forward-most points) matched, at a few scales and pitches."""
    tip_m = neutral[np.argmax(neutral[:, 2])]
    tip_r = rig.neutral[np.argmax(rig.neutral[:, 2])]
    out = []
    for s in (0.85, 1.0, 1.15):
        for pitch in (-0.15, 0.0, 0.15):
            R = _rotation(np.array([pitch, 0.0, 0.0]))
            out.append(Similarity(s, R, tip_r - s * R @ tip_m))
    return out


def bind_capture(take: Take, rig: Rig, layout: MarkerLayout | None = None, span: tuple[int, int] | None = None,
                 options: BindOptions = BindOptions(), rom: Take | None = None) -> BindResult:
    """Bind every marker of ``take`` to ``rig``'s surface; ``layout`` (the rig's own markers) gives landmarks;
    ``rom`` (a range-of-motion take of the same markers), when given, is where rigidity is measured."""
    span = span or neutral_span(take, options.window, options.search)
    if not 0 <= span[0] < span[1] <= take.n_frames:
        raise BindError(f"span {span} is outside the take's {take.n_frames} frames")
    neutral = span_neutral(take, span)
    if rom is not None:
        missing = sorted(set(take.labels) - set(rom.labels))
        if missing:
            raise BindError(f"the range-of-motion take lacks markers {missing[:5]}")
        dev, stable = stability(rom.select(take.labels), neutral, options)
    else:
        dev, stable = stability(take, neutral, options)
    surface = Surface(rig.neutral, rig.triangles)
    anchors, src, dst = _hint_anchors(take.labels, neutral, layout if options.use_names else None, rig)
    starts = ([_umeyama(src, dst, True)] if len(anchors) >= 4 else []) + _starts(neutral, rig)
    best: tuple[float, Similarity] | None = None
    for start in starts:
        sim, rms = _icp(neutral, surface, start, options.trim)
        if best is None or rms < best[0]:
            best = (rms, sim)
    assert best is not None
    rms, sim = best
    use = np.ones(take.n_markers, dtype=bool)
    for _ in range(3):  # markers off the face (a headband) must not pull the fit: refit without them
        far = surface.closest(sim.apply(neutral))[0] / sim.scale > options.max_distance
        if (far == ~use).all() or far.all():
            break
        use = ~far
        sim, rms = _icp(neutral[use], surface, sim, options.trim)
    p = sim.apply(neutral)
    dist, tri, bary = surface.closest(p)
    on_edge = surface.on_boundary(tri, bary, eps=1e-4)
    # distances in the capture's millimetres, not the rig's scale
    dist_mm = dist / sim.scale
    out = []
    for i, lab in enumerate(take.labels):
        reason = ""
        if dist_mm[i] > options.max_distance:
            reason = f"{dist_mm[i]:.1f} mm from the rig's surface (> {options.max_distance} mm)"
        elif on_edge[i] and dist_mm[i] > options.boundary_mm:
            reason = f"{dist_mm[i]:.1f} mm beyond the rig's open boundary (off the rig's face)"
        out.append(MarkerBinding(lab, not reason, int(tri[i]), bary[i], float(dist_mm[i]), float(dev[i]),
                                 bool(stable[i]) and not reason, reason))
    return BindResult(out, sim, span, anchors, rms / sim.scale)
