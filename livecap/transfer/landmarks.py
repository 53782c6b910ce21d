"""Automated landmark detection (Xiang et al. 2008 §3.1, Algorithm 1).

For each landmark of the generic face: take its geodesic neighbourhood (radius ``r_d = 6 %`` of
the eye width; exact geodesics of Surazhsky et al. 2005, the algorithm Xiang cite, through
libigl), register that patch to the target surface by rigid ICP from nine initial offsets
(``{-r_d/2, 0, +r_d/2}`` in the two directions orthogonal to the view), keep the registration
with the smallest error, move the landmark with it and take the closest target point whose
normal is within 60 degrees of the moved landmark's normal.

Choices the paper leaves open, documented here:

* the view direction of the offsets is the landmark's own surface normal (for frontal
  landmarks this is the paper's view direction; for temples and jaw it keeps the offsets on
  the surface);
* on a patch of a smooth region every offset registers equally well; among registrations whose
  error is within 5 % (plus 1e-6 of the radius) of the best, the one moving the landmark least
  wins, so a tie never drags a landmark half a radius sideways;
* a patch much smaller than the mesh's edges would hold one or two vertices and register
  nothing, so the patch is sampled on the mesh subdivided (midpoints, libigl ``upsample``)
  until its edges are under a third of the radius.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import igl
import numpy as np

from livecap.core.markers import MarkerLayout
from livecap.transfer.surface import Surface, unit, vertex_normals
from solvers.rigid import kabsch

# Eye-corner marker pairs (outer, inner) by naming scheme: 68-landmark multi-PIE numbering as in
# ICT's markers.json (36-39 the subject's right eye, 42-45 the left), and common mocap names.
EYE_CORNERS: list[tuple[str, str]] = [
    ("M36_eye", "M39_eye"), ("M45_eye", "M42_eye"),
    ("EYE_OUT_L", "EYE_IN_L"), ("EYE_OUT_R", "EYE_IN_R"),
    ("LEyeOuter", "LEyeInner"), ("REyeOuter", "REyeInner"),
]
# Without eye corners: eye width as a fraction of the left-right extent of the marker sites.
# 0.178 is ICT's (26.2 mm eyes, 147.2 mm between its outermost jaw-contour markers).
EYE_WIDTH_FALLBACK = 0.178


def eye_width(layout: MarkerLayout, neutral: np.ndarray, corners: Sequence[tuple[str, str]] = EYE_CORNERS,
              fallback: float = EYE_WIDTH_FALLBACK) -> tuple[float, str]:
    """Average eye width ``w_eye`` (mm) from the layout's eye-corner markers, and how it was found.

    Without any known corner pair: ``fallback`` x the x-extent (left-right in livecap's
    convention) of the marker sites.
    """
    sites = layout.sampling_matrix(len(neutral)) @ neutral
    pos = dict(zip(layout.labels, sites, strict=True))
    widths = [float(np.linalg.norm(pos[a] - pos[b])) for a, b in corners if a in pos and b in pos]
    if widths:
        return float(np.mean(widths)), f"eye corners ({len(widths)} eyes)"
    return fallback * float(np.ptp(sites[:, 0])), f"{fallback:g} x marker width (no eye-corner markers)"


@dataclass
class LandmarkResult:
    """Detected landmarks on the target surface."""

    points: np.ndarray  # n x 3 on the target
    triangles: np.ndarray  # n target triangles
    barycentric: np.ndarray  # n x 3
    error: np.ndarray  # n ICP registration RMS of the best state (mm)
    moved: np.ndarray  # n distance from the (pre-aligned) generic landmark to the detected one
    compatible: np.ndarray  # n bool: passed the normal-compatibility test
    patch_points: np.ndarray  # n, points in each geodesic patch


def geodesic_patch(surface: Surface, vertex: int, radius: float, max_upsample: int = 4
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Points and normals of the surface within geodesic distance ``radius`` of ``vertex``.

    A geodesic path shorter than ``radius`` stays inside the Euclidean ball of that radius, so
    the exact geodesic distances are computed on the sub-mesh cut out by the ball only.
    """
    centre = surface.vertices[vertex]
    sub_v, sub_f, src = surface.vertices, surface.triangles, vertex
    for level in range(max_upsample + 1):
        e = np.linalg.norm(sub_v[sub_f] - sub_v[np.roll(sub_f, 1, axis=1)], axis=2)
        near = np.linalg.norm(sub_v - centre, axis=1) <= radius + e.max()
        sub_v, sub_f, _, keep = igl.remove_unreferenced(sub_v, sub_f[near[sub_f].any(axis=1)])
        src = int(np.where(np.asarray(keep).ravel() == src)[0][0])
        e = np.linalg.norm(sub_v[sub_f] - sub_v[np.roll(sub_f, 1, axis=1)], axis=2)
        if e.mean() <= radius / 3 or level == max_upsample:
            break
        sub_v, sub_f = igl.upsample(sub_v, sub_f, 1)  # original vertices keep their indices
    sub_f = np.ascontiguousarray(sub_f, dtype=np.int64)
    dist = igl.exact_geodesic(sub_v, sub_f, np.array([src], dtype=np.int64), np.array([], dtype=np.int64),
                              np.arange(len(sub_v), dtype=np.int64), np.array([], dtype=np.int64))
    inside = dist <= radius
    return sub_v[inside], vertex_normals(sub_v, sub_f)[inside]


def _rigid_icp(points: np.ndarray, normals: np.ndarray, target: Surface, R0: np.ndarray, t0: np.ndarray,
               cos_max: float, iterations: int, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rigid ICP of one patch from several initial states (R0 (s, 3, 3), t0 (s, 3)) at once
    (Besl & McKay; closest points on triangles, normal-compatible pairs only, Kabsch steps).

    Returns per start (R (s, 3, 3), t (s, 3), RMS point-to-surface distance (s,)), x -> R x + t.
    Points whose closest point fails the normal test count as misses at the patch's size, so a
    registration that slides a patch onto the wrong side of a lip loses.
    """
    s, k = len(t0), len(points)
    R = np.array(R0, dtype=np.float64)
    t = np.array(t0, dtype=np.float64)
    miss = float(np.ptp(points, axis=0).max()) + 1e-12
    active = np.ones(s, dtype=bool)

    def match(R, t):
        p = np.einsum("sij,kj->ski", R, points) + t[:, None, :]
        dist, tri, bary = target.closest(p.reshape(-1, 3))
        n = np.einsum("sij,kj->ski", R, normals).reshape(-1, 3)
        ok = np.einsum("ij,ij->i", target.normal_at(tri, bary), n) > cos_max
        return p, dist.reshape(s, k), tri, bary, ok.reshape(s, k)

    for _ in range(iterations):
        p, _, tri, bary, ok = match(R, t)
        q = target.point(tri, bary).reshape(s, k, 3)
        w = ok.astype(np.float64) + 1e-12
        dR, dt = kabsch(p, q, w)
        step = np.linalg.norm(np.einsum("sij,sj->si", dR - np.eye(3), p.mean(1)) + dt, axis=1)
        upd = active & (ok.sum(1) >= 3)
        R[upd] = np.einsum("sij,sjk->sik", dR, R)[upd]
        t[upd] = (np.einsum("sij,sj->si", dR, t) + dt)[upd]
        active &= step > tol
        if not active.any():
            break
    _, dist, _, _, ok = match(R, t)
    return R, t, np.sqrt(np.mean(np.where(ok, dist, np.maximum(dist, miss)) ** 2, axis=1))


def detect_landmarks(source: Surface, sites: np.ndarray, site_vertices: np.ndarray, target: Surface,
                     radius: float | Sequence[float], max_angle: float = 60.0, iterations: int = 20,
                     tie: float = 0.05, max_points: int = 64,
                     progress: Callable[[int, int], None] | None = None) -> LandmarkResult:
    """Algorithm 1 of Xiang et al. 2008 for landmark ``sites`` (n x 3) on ``source``.

    ``site_vertices`` (n,) are the source vertices nearest each site (the patch centres).
    ``radius``: the patch radius r_d (mm), or several, coarse to fine: each level starts its nine
    states around the previous level's registration (a livecap extension; one radius is the
    paper). Both surfaces must already be roughly aligned: the patches only correct offsets of
    about ``radius``, so :func:`livecap.transfer.transfer` runs the similarity of
    :mod:`livecap.transfer.align` and the smooth warp of :mod:`livecap.transfer.warp` first.
    """
    radii = [float(radius)] if np.ndim(radius) == 0 else [float(r) for r in np.ravel(radius)]
    n = len(sites)
    cos_max = np.cos(np.radians(max_angle))
    _, tri0, bary0 = source.closest(sites)
    site_normals = source.normal_at(tri0, bary0)
    moved_sites = np.zeros((n, 3))
    moved_normals = np.zeros((n, 3))
    errors = np.zeros(n)
    sizes = np.zeros(n, dtype=int)
    grid = np.array([(a, b) for a in (0.0, -0.5, 0.5) for b in (0.0, -0.5, 0.5)])
    for i in range(n):
        R_best, t_best, m_best = np.eye(3), np.zeros(3), sites[i]
        for r in radii:
            pts, nrm = geodesic_patch(source, int(site_vertices[i]), r)
            sizes[i] = len(pts)
            if len(pts) > max_points:  # a deterministic thinning: the patch keeps its extent at a fraction of the cost
                keep = np.linspace(0, len(pts) - 1, max_points).round().astype(int)
                pts, nrm = pts[keep], nrm[keep]
            nz = R_best @ site_normals[i]
            u = unit(np.cross(nz, [0.0, 1.0, 0.0] if abs(nz[1]) < 0.9 else [1.0, 0.0, 0.0]))
            v = np.cross(nz, u)
            t0 = t_best + r * (grid[:, :1] * u + grid[:, 1:] * v)
            R, t, err = _rigid_icp(pts, nrm, target, np.tile(R_best, (len(grid), 1, 1)), t0, cos_max, iterations,
                                   1e-4 * r)
            m = np.einsum("sij,j->si", R, sites[i]) + t
            moved = np.linalg.norm(m - m_best, axis=1)
            close = np.where(err <= err.min() * (1 + tie) + 2e-3 * r)[0]
            j = close[np.argmin(moved[close])]
            R_best, t_best, m_best, errors[i] = R[j], t[j], m[j], err[j]
        moved_sites[i], moved_normals[i] = m_best, R_best @ site_normals[i]
        if progress is not None:
            progress(i + 1, n)
    _, tri, bary, ok = target.closest_compatible(moved_sites, moved_normals, max_angle)
    points = target.point(tri, bary)
    return LandmarkResult(points, tri, bary, errors, np.linalg.norm(points - sites, axis=1), ok, sizes)
