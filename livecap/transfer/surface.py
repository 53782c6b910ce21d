"""A triangle mesh prepared for the closest-point queries rig transfer makes thousands of times.

Closest points on triangles come from libigl's AABB tree (built once per surface); the
normal-compatibility test of Xiang et al. 2008 §3.1 (normals closer than 60 degrees, "to get
better matches in regions such as the lips") uses smooth, area-weighted vertex normals
interpolated at the closest point. Hits on the target's open boundary are reported, because a
closest point on a boundary edge is where a surface that extends further (a neck, the back of a
head) projects, not a real correspondence (the usual rejection rule of non-rigid ICP).
"""

from __future__ import annotations

import igl
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


def unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


def face_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unnormalised face normals (length = twice the area)."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    return np.cross(b - a, c - a)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, unit length (zero for unreferenced vertices)."""
    fn = face_normals(vertices, triangles)
    out = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(out, triangles[:, k], fn)
    return unit(out)


def mean_edge_length(vertices: np.ndarray, triangles: np.ndarray) -> float:
    e = np.concatenate([vertices[triangles[:, 1]] - vertices[triangles[:, 0]],
                        vertices[triangles[:, 2]] - vertices[triangles[:, 1]],
                        vertices[triangles[:, 0]] - vertices[triangles[:, 2]]])
    return float(np.linalg.norm(e, axis=1).mean())


def barycentric(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of ``points`` (k x 3) in triangles ``tri`` (k,), clipped to the triangle."""
    a, b, c = (vertices[triangles[tri, k]] for k in range(3))
    v0, v1, v2 = b - a, c - a, points - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    ok = np.abs(den) > 1e-300
    den = np.where(ok, den, 1.0)
    v = np.where(ok, (d11 * d20 - d01 * d21) / den, 0.0)
    w = np.where(ok, (d00 * d21 - d01 * d20) / den, 0.0)
    out = np.clip(np.stack([1.0 - v - w, v, w], axis=1), 0.0, None)
    return out / out.sum(axis=1, keepdims=True)


def boundary_vertices(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """Vertices on an edge used by exactly one triangle."""
    e = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    mask = np.zeros(n_vertices, dtype=bool)
    mask[uniq[counts == 1].ravel()] = True
    return mask


def adjacency(triangles: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    i = np.concatenate([triangles[:, 0], triangles[:, 1], triangles[:, 2]])
    j = np.concatenate([triangles[:, 1], triangles[:, 2], triangles[:, 0]])
    a = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(n_vertices, n_vertices))
    return ((a + a.T) > 0).astype(np.float64).tocsr()


class Surface:
    """Vertices, triangles, normals, boundary and an AABB tree for closest points on triangles."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or len(self.triangles) == 0:
            raise ValueError("a surface needs V x 3 vertices and at least one triangle")
        self.normals = vertex_normals(self.vertices, self.triangles)
        self.boundary = boundary_vertices(self.triangles, len(self.vertices))
        # per triangle: is the edge opposite corner k a boundary edge?
        tb = self.boundary[self.triangles]
        self._opp_boundary = np.stack([tb[:, 1] & tb[:, 2], tb[:, 2] & tb[:, 0], tb[:, 0] & tb[:, 1]], axis=1)
        self._tree = igl.AABB()
        self._tree.init(self.vertices, self.triangles)
        self._kd: cKDTree | None = None
        self._vertex_faces: sp.csr_matrix | None = None

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    def edge_length(self) -> float:
        return mean_edge_length(self.vertices, self.triangles)

    @property
    def max_edge(self) -> float:
        V, F = self.vertices, self.triangles
        return float(max(np.linalg.norm(V[F[:, a]] - V[F[:, b]], axis=1).max() for a, b in ((0, 1), (1, 2), (2, 0))))

    # ------------------------------------------------------------------ queries
    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(distance, triangle, barycentric) of the closest surface point to each of ``points``."""
        pts = np.ascontiguousarray(np.atleast_2d(points), dtype=np.float64)
        d2, tri, _ = self._tree.squared_distance(self.vertices, self.triangles, pts)
        tri = np.asarray(tri, dtype=np.int64)
        bary = barycentric(pts, self.vertices, self.triangles, tri)
        return np.sqrt(np.maximum(d2, 0.0)), tri, bary

    def point(self, tri: np.ndarray, bary: np.ndarray, vertices: np.ndarray | None = None) -> np.ndarray:
        v = self.vertices if vertices is None else vertices
        return np.einsum("ik,ikj->ij", bary, v[self.triangles[tri]])

    def normal_at(self, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
        return unit(np.einsum("ik,ikj->ij", bary, self.normals[self.triangles[tri]]))

    def on_boundary(self, tri: np.ndarray, bary: np.ndarray, eps: float = 1e-7) -> np.ndarray:
        """Whether a surface point lies on the open boundary (on a boundary edge or vertex)."""
        on_edge = (self._opp_boundary[tri] & (bary < eps)).any(axis=1)
        on_vertex = (self.boundary[self.triangles[tri]] & (bary > 1.0 - eps)).any(axis=1)
        return on_edge | on_vertex

    def closest_compatible(self, points: np.ndarray, normals: np.ndarray, max_angle: float = 60.0,
                           candidates: int = 32) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closest point whose normal is within ``max_angle`` degrees of ``normals`` (Xiang §3.1).

        Where the plain closest point fails the test, the nearest vertices (k-d tree) with a
        compatible normal are tried and the point is projected onto their triangles. Returns
        (distance, triangle, barycentric, compatible).
        """
        points = np.atleast_2d(points)
        normals = unit(np.atleast_2d(normals))
        cos_max = np.cos(np.radians(max_angle))
        dist, tri, bary = self.closest(points)
        ok = np.einsum("ij,ij->i", self.normal_at(tri, bary), normals) > cos_max
        bad = np.where(~ok)[0]
        if len(bad):
            if self._kd is None:
                self._kd = cKDTree(self.vertices)
                n_t = len(self.triangles)
                self._vertex_faces = sp.csr_matrix(
                    (np.ones(3 * n_t), (self.triangles.ravel(), np.repeat(np.arange(n_t), 3))),
                    shape=(self.n_vertices, n_t))
            k = min(candidates, self.n_vertices)
            _, idx = self._kd.query(points[bad], k=k)
            idx = np.atleast_2d(idx).reshape(len(bad), k)
            for row, i in enumerate(bad):
                comp = idx[row][self.normals[idx[row]] @ normals[i] > cos_max]
                if not len(comp):
                    continue
                faces = self._vertex_faces[comp[0]].indices
                fn = unit(face_normals(self.vertices, self.triangles[faces]))
                faces = faces[fn @ normals[i] > cos_max] if (fn @ normals[i] > cos_max).any() else faces
                d2, j, _ = igl.point_mesh_squared_distance(points[i:i + 1], self.vertices, self.triangles[faces])
                t = faces[int(j[0])]
                b = barycentric(points[i:i + 1], self.vertices, self.triangles, np.array([t]))
                dist[i], tri[i], bary[i], ok[i] = np.sqrt(max(float(d2[0]), 0.0)), t, b[0], True
        return dist, tri, bary, ok
