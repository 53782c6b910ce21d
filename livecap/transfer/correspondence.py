"""Dense correspondence from the deformed generic face to the new face's own topology (Xiang §3.2, end).

"For each vertex on the individual facial model, we find its corresponding closest surface point
on the deformed model, and use the triangle and the barycentric coordinates for its
parameterization on the generic facial model." Displacements of any expression are then carried
to the new face by barycentric interpolation (Xiang §3.3, last paragraph).

Where the new face extends beyond the generic one (a neck under a face-only rig, the back of a
scalp) its vertices are far from the deformed generic; their displacement fades out smoothly
between ``near`` and ``far`` (distances in mm), so the neck does not drag along with the jaw's
boundary row.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from livecap.core.markers import MarkerLayout
from livecap.transfer.surface import Surface


@dataclass
class Correspondence:
    """Each target vertex as a point of the generic (deformed) surface: triangle + barycentric."""

    source_triangles: np.ndarray  # F x 3 of the generic mesh
    triangles: np.ndarray  # Vt, index into source_triangles
    barycentric: np.ndarray  # Vt x 3
    distance: np.ndarray  # Vt, mm from the target vertex to the deformed generic
    weight: np.ndarray  # Vt in [0, 1]: how much of the generic's displacement the vertex takes
    compatible: np.ndarray  # Vt bool: the matched point passed the normal test

    def matrix(self, n_source: int) -> sp.csr_matrix:
        """Vt x Vs sparse matrix carrying generic per-vertex fields onto the target's vertices."""
        vt = len(self.triangles)
        rows = np.repeat(np.arange(vt), 3)
        cols = self.source_triangles[self.triangles].ravel()
        vals = (self.barycentric * self.weight[:, None]).ravel()
        return sp.csr_matrix((vals, (rows, cols)), shape=(vt, n_source))

    def carry(self, fields: np.ndarray) -> np.ndarray:
        """Displacement field(s) (Vs, 3) or (K, Vs, 3) on the generic -> the same on the target."""
        f = np.asarray(fields, dtype=np.float64)
        M = self.matrix(f.shape[-2])
        if f.ndim == 2:
            return np.asarray(M @ f)
        return np.stack([np.asarray(M @ x) for x in f])


def smoothstep_falloff(distance: np.ndarray, near: float, far: float) -> np.ndarray:
    """1 up to ``near``, 0 from ``far``, C1-smooth in between."""
    if far <= near:
        return (distance <= near).astype(np.float64)
    s = np.clip((far - distance) / (far - near), 0.0, 1.0)
    return s * s * (3 - 2 * s)


def dense_correspondence(deformed: Surface, target: Surface, near: float, far: float,
                         max_angle: float = 60.0) -> Correspondence:
    """Closest normal-compatible point of the deformed generic for every vertex of ``target``."""
    dist, tri, bary, ok = deformed.closest_compatible(target.vertices, target.normals, max_angle)
    return Correspondence(deformed.triangles, tri, bary, dist, smoothstep_falloff(dist, near, far), ok)


def place_markers(layout: MarkerLayout, deformed: Surface, target: Surface, max_angle: float = 60.0
                  ) -> tuple[MarkerLayout, np.ndarray]:
    """The generic's markers on the new face: same labels and stable flags, bound to vertices.

    Each marker site is taken on the deformed generic (same triangle and barycentric as on the
    generic), projected to the closest normal-compatible point of the new face, and bound to the
    nearest vertex of that triangle (markers.json stores vertex bindings). Returns the layout and
    the distance (mm) from each projected site to its bound vertex.
    """
    sites = layout.sampling_matrix(deformed.n_vertices) @ deformed.vertices
    normals = layout.sampling_matrix(deformed.n_vertices) @ deformed.normals
    _, tri, bary, _ = target.closest_compatible(sites, normals, max_angle)
    points = target.point(tri, bary)
    corners = target.triangles[tri]  # (n, 3)
    d = np.linalg.norm(target.vertices[corners] - points[:, None, :], axis=2)
    best = corners[np.arange(len(corners)), np.argmin(d, axis=1)]
    return (MarkerLayout.from_vertices(list(layout.labels), best, layout.stable.copy(), units="mm"),
            d.min(axis=1))
