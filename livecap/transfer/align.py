"""Global pre-alignment of the generic face to the new face (before Xiang et al. 2008 §3.1).

Xiang's landmark detector assumes "the input models are roughly globally aligned". Scans and
rigs come in different positions (and, when units are unknown, scales), so the generic neutral
is first brought onto the target by a trimmed similarity ICP (Besl & McKay; scale as in Umeyama
1991): closest points on the target's triangles, pairs failing the 60-degree normal test or
landing on the target's open boundary rejected, and the worst ``1 - trim`` of the rest dropped,
which lets faces cut differently (with or without neck, ears, scalp) align on what they share.

Both faces are assumed to face roughly the same way (livecap's convention: +y up, +z out of the
face); ICP starts from two guesses, the forward-most points (nose tips) matched and the
centroids matched, and keeps the one with the smaller trimmed residual.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livecap.transfer.surface import Surface
from solvers.rigid import kabsch


@dataclass(frozen=True)
class Similarity:
    """x -> scale * R x + t."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    @classmethod
    def identity(cls) -> Similarity:
        return cls(1.0, np.eye(3), np.zeros(3))

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points) @ self.rotation.T + self.translation

    def apply_vectors(self, vectors: np.ndarray) -> np.ndarray:
        """Displacements: scaled and rotated, not translated."""
        return self.scale * np.asarray(vectors) @ self.rotation.T

    def then(self, other: Similarity) -> Similarity:
        """``other`` applied after ``self``."""
        return Similarity(other.scale * self.scale, other.rotation @ self.rotation,
                          other.apply(self.translation))


def _umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> Similarity:
    R, _ = kabsch(src, dst)
    cs, cd = src.mean(0), dst.mean(0)
    s = 1.0
    if with_scale:
        s = float(np.sum((dst - cd) * ((src - cs) @ R.T)) / max(np.sum((src - cs) ** 2), 1e-300))
    return Similarity(s, R, cd - s * R @ cs)


def _rotation(w: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(w))
    if angle == 0.0:
        return np.eye(3)
    k = w / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _point_to_plane(p: np.ndarray, q: np.ndarray, n: np.ndarray, with_scale: bool) -> Similarity:
    """One linearised step minimising sum ((s R p + t - q) . n)^2 (Chen & Medioni; Low 2004)."""
    J = np.hstack([np.cross(p, n), n] + ([np.einsum("ij,ij->i", p, n)[:, None]] if with_scale else []))
    r = np.einsum("ij,ij->i", q - p, n)
    H = J.T @ J
    H += np.eye(len(H)) * (1e-9 * np.trace(H) / len(H))
    x = np.linalg.solve(H, J.T @ r)
    return Similarity(1.0 + (x[6] if with_scale else 0.0), _rotation(x[:3]), x[3:6])


def icp(source: Surface, target: Surface, start: Similarity, with_scale: bool = True, trim: float = 0.8,
        max_angle: float = 60.0, iterations: int = 80, samples: int = 3000,
        tol: float = 1e-10, point_to_point: int = 10) -> tuple[Similarity, float]:
    """Trimmed ICP from ``start``: ``point_to_point`` closed-form steps (robust far from the
    answer), then point-to-plane steps (fast near it). Returns the similarity and the trimmed RMS (mm)."""
    rng = np.random.default_rng(0)
    idx = np.arange(source.n_vertices)
    if len(idx) > samples:
        idx = np.sort(rng.choice(idx, samples, replace=False))
    pts, nrm = source.vertices[idx], source.normals[idx]
    cos_max = np.cos(np.radians(max_angle))
    current, rms = start, np.inf
    for it in range(iterations):
        p = current.apply(pts)
        dist, tri, bary = target.closest(p)
        n = nrm @ current.rotation.T
        ok = (np.einsum("ij,ij->i", target.normal_at(tri, bary), n) > cos_max) & ~target.on_boundary(tri, bary)
        if ok.sum() < 10:
            break
        keep = np.where(ok)[0]
        keep = keep[dist[keep] <= np.quantile(dist[keep], trim)]
        q = target.point(tri[keep], bary[keep])
        rms = float(np.sqrt(np.mean(dist[keep] ** 2)))
        if it < point_to_point:
            step = _umeyama(p[keep], q, with_scale)
        else:
            step = _point_to_plane(p[keep], q, target.normal_at(tri[keep], bary[keep]), with_scale)
        current = current.then(step)
        change = abs(step.scale - 1) + np.linalg.norm(step.rotation - np.eye(3)) + \
            np.linalg.norm(step.translation) / max(np.ptp(p, axis=0).max(), 1e-300)
        if change < tol:
            break
    return current, rms


def prealign(source: Surface, target: Surface, mode: str = "similarity", trim: float = 0.8,
             max_angle: float = 60.0) -> Similarity:
    """The similarity (``mode="similarity"``), rigid motion (``"rigid"``) or identity (``"none"``)
    bringing ``source`` onto ``target``."""
    if mode == "none":
        return Similarity.identity()
    if mode not in ("similarity", "rigid"):
        raise ValueError(f"unknown pre-alignment {mode!r} (similarity, rigid or none)")
    sv, tv = source.vertices, target.vertices
    # a first scale guess only when the two meshes are clearly in different units
    ratio = np.ptp(tv[:, 0]) / max(np.ptp(sv[:, 0]), 1e-300)
    s0 = ratio if (mode == "similarity" and not 0.5 < ratio < 2.0) else 1.0
    tips = (sv[np.argmax(sv[:, 2])], tv[np.argmax(tv[:, 2])])
    cents = (sv.mean(0), tv.mean(0))
    best: tuple[float, Similarity] | None = None
    for a, b in (tips, cents):
        start = Similarity(s0, np.eye(3), b - s0 * a)
        sim, rms = icp(source, target, start, mode == "similarity", trim, max_angle)
        if best is None or rms < best[0]:
            best = (rms, sim)
    assert best is not None
    return best[1]
