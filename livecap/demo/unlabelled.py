"""Unlabelled clouds from labelled takes, as an optical system would hand them over, and the
scores of a labelling against the truth they came from.

``scramble`` strips the labels, shuffles the points every frame, adds ghost points and
occlusion bursts; the returned ``source`` says which label (or -1: ghost, empty slot) each
column of the cloud take really is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livecap.core.take import Take


@dataclass
class ScrambledTake:
    cloud: Take  # columns "*0".. mean nothing; each frame's points are its valid columns
    source: np.ndarray  # T x K: the label index each column holds, -1 for a ghost or empty slot
    labels: list[str]  # the labels ``source`` indexes
    occluded: Take  # the labelled take with the same occlusion bursts (the labelled baseline)


def scramble(take: Take, seed: int = 0, ghosts: int = 2, occlusion: float = 0.05,
             ghost_margin_mm: float = 10.0) -> ScrambledTake:
    """Strip labels, add occlusion bursts (3-40 frames) until ``occlusion`` of marker-frames are
    missing, add ``ghosts`` points per frame uniformly in the markers' bounding box grown by
    ``ghost_margin_mm``, and shuffle every frame's points."""
    rng = np.random.default_rng(seed)
    T, n = take.n_frames, take.n_markers
    valid = take.valid.copy()
    budget = occlusion * valid.size
    while (~valid).sum() < budget:
        length = int(rng.integers(3, 41))
        start = int(rng.integers(0, max(1, T - length)))
        valid[start:start + length, rng.integers(0, n)] = False
    K = n + ghosts
    pos = np.zeros((T, K, 3))
    ok = np.zeros((T, K), dtype=bool)
    source = np.full((T, K), -1, dtype=np.int64)
    for f in range(T):
        vis = np.flatnonzero(valid[f])
        pts = take.positions[f, vis]
        lo, hi = (pts.min(0), pts.max(0)) if len(pts) else (np.zeros(3), np.zeros(3))
        ghost = rng.uniform(lo - ghost_margin_mm, hi + ghost_margin_mm, (ghosts, 3))
        allp = np.vstack([pts, ghost])
        src = np.concatenate([vis, np.full(ghosts, -1)])
        order = rng.permutation(len(allp))
        k = len(allp)
        pos[f, :k] = allp[order]
        ok[f, :k] = True
        source[f, :k] = src[order]
    cloud = Take([f"*{i}" for i in range(K)], pos, ok, take.rate, take.first_frame)
    occluded = Take(list(take.labels), take.positions, valid, take.rate, take.first_frame)
    return ScrambledTake(cloud, source, list(take.labels), occluded)


@dataclass
class LabelScores:
    right: float  # fraction of visible marker-frames given their own label
    longest_swap: int  # longest run of consecutive frames a label is given another marker's point
    unlabelled: int  # visible marker-frames left without a label
    ghost_labelled: int  # marker-frames given a ghost point
    visible: int

    def line(self) -> str:
        return (f"right labels {100 * self.right:.3f} % of {self.visible} visible marker-frames, "
                f"longest swap {self.longest_swap} frames, visible unlabelled {self.unlabelled}, "
                f"ghosts labelled {self.ghost_labelled}")


def in_a_crowd(take: Take, frames: int, ghosts: int, seed: int = 0) -> list[np.ndarray]:
    """Each frame's visible face markers shuffled among ``ghosts`` points uniform in a 2 m cube about the
    face: a body capture around it, as a facial labeller meets it on a full-body stage."""
    rng = np.random.default_rng(seed)
    centre = np.nanmean(take.positions[0], 0)
    out = []
    for f in range(frames):
        face = take.positions[f][take.valid[f]]
        cloud = np.vstack([face, centre + rng.uniform(-1000, 1000, (ghosts, 3))])
        out.append(cloud[rng.permutation(len(cloud))])
    return out


def score(columns: np.ndarray, source: np.ndarray) -> LabelScores:
    """``columns`` (T x n): the cloud column given to each label (-1: missing)."""
    T, n = columns.shape
    truth_col = np.full((T, n), -1, dtype=np.int64)
    f, c = np.nonzero(source >= 0)
    truth_col[f, source[f, c]] = c
    visible = truth_col >= 0
    got = np.where(columns >= 0, np.take_along_axis(source, np.maximum(columns, 0), 1), -2)
    right = visible & (got == np.arange(n)[None, :])
    wrong = (columns >= 0) & (got != np.arange(n)[None, :])
    longest = 0
    for i in range(n):
        run = 0
        for w in wrong[:, i]:
            run = run + 1 if w else 0
            longest = max(longest, run)
    ghost = int(((columns >= 0) & (got == -1)).sum())
    unlabelled = int((visible & (columns < 0)).sum())
    return LabelScores(float(right.sum() / max(visible.sum(), 1)), longest, unlabelled, ghost, int(visible.sum()))


def faster_larger(rig, layout, factor: float = 1.2, seconds: float = 20.0, seed: int = 11) -> tuple[Take, np.ndarray]:
    """A performance ``factor`` times faster (curves and head motion generated at rate/factor,
    played at the rate) with ``factor`` times the weights and head motion of the default one, by
    the same actor (the generator's default actor_seed). Returns the take and its true weights."""
    from livecap.demo.performance import PerformanceSettings, perform, weight_curves

    base = PerformanceSettings()
    s = PerformanceSettings(seconds=seconds, rate=base.rate / factor, head_degrees=base.head_degrees * factor,
                            head_mm=base.head_mm * factor, seed=seed)
    W = factor * weight_curves(list(rig.names), rig.upper, s, np.random.default_rng(seed))
    perf = perform(rig, layout, s, weights=W)
    take = perf.take
    return Take(take.labels, take.positions, take.valid, base.rate, take.first_frame), W
