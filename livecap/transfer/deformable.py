"""Deformable model: the generic face deformed into the shape of the new face (Xiang et al. 2008 §3.2).

Each iteration solves Xiang's Eq. 5 for the displacement ``d`` of the current mesh,

    (k_s K + k_b K M^-1 K + k_m S^T S + k_c C) d = k_m S^T (m' - S x) + k_c C (p' - x),

the variational form of the linearised stretching + bending energy (Botsch & Sorkine 2008) with
the landmark and closest-point potentials: K = -L is the cotangent stiffness matrix (libigl
``cotmatrix``), M the Voronoi mass matrix, so K and K M^-1 K are the symmetric forms of Xiang's
-L and L^2 for the Laplace-Beltrami operator L = M^-1 L_c; S samples the landmarks (triangle +
barycentric rows, Xiang's matrix M); C is diagonal with 1 where a vertex's closest target point
passes the normal test and is not on the target's open boundary, 0 elsewhere. The matrix is
symmetric positive definite and factored with a sparse LU (SuperLU, no CHOLMOD needed).

Annealing (Xiang §3.2): 10 iterations, weights varied linearly: k_s 1 -> 1e-3, k_b 1e-9 -> 1e-12,
k_m 100 -> 1000, k_c 0 -> 3000; each iteration starts from the last one's result.

Units. Stretching and the point potentials scale alike with the mesh (both ~ length^2), the
bending term does not, and per-vertex weights only mean something against the stiffness of a
known edge length. The paper's constants are therefore applied to the mesh scaled to unit mean
edge length; the result is scaled back. At that scale the bending weights of the paper are
negligible (they are kept for fidelity and can be raised through :class:`Schedule`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import igl
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from livecap.transfer.surface import Surface, vertex_normals


@dataclass(frozen=True)
class Schedule:
    """Xiang's annealing schedule: (start, end) of each weight, varied linearly."""

    iterations: int = 10
    k_s: tuple[float, float] = (1.0, 1e-3)
    k_b: tuple[float, float] = (1e-9, 1e-12)
    k_m: tuple[float, float] = (100.0, 1000.0)
    k_c: tuple[float, float] = (0.0, 3000.0)

    def weights(self, i: int) -> tuple[float, float, float, float]:
        f = i / max(self.iterations - 1, 1)
        return tuple(a + f * (b - a) for a, b in (self.k_s, self.k_b, self.k_m, self.k_c))  # type: ignore


@dataclass
class DeformResult:
    vertices: np.ndarray  # V x 3: the generic topology in the target's shape (mm)
    rms: list[float] = field(default_factory=list)  # per iteration: RMS distance of matched vertices (mm)
    matched: list[float] = field(default_factory=list)  # per iteration: fraction of vertices with a closest point
    landmark_error: list[float] = field(default_factory=list)  # per iteration: RMS landmark residual (mm)


def closest_targets(vertices: np.ndarray, triangles: np.ndarray, target: Surface, max_angle: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest target point of every vertex, whether it is usable, and its distance."""
    dist, tri, bary = target.closest(vertices)
    n = vertex_normals(vertices, triangles)
    ok = np.einsum("ij,ij->i", target.normal_at(tri, bary), n) > np.cos(np.radians(max_angle))
    ok &= ~target.on_boundary(tri, bary)
    return target.point(tri, bary), ok, dist


def deform(vertices: np.ndarray, triangles: np.ndarray, landmarks: sp.spmatrix, landmark_targets: np.ndarray,
           target: Surface, schedule: Schedule | None = None, max_angle: float = 60.0,
           progress: Callable[[int, int], None] | None = None) -> DeformResult:
    """Deform (``vertices``, ``triangles``) onto ``target``, landmarks ``landmarks @ x`` onto ``landmark_targets``.

    ``landmarks`` is an n x V sampling matrix (rows of barycentric weights); drop landmarks that
    failed detection before calling.
    """
    schedule = schedule or Schedule()
    x = np.asarray(vertices, dtype=np.float64).copy()
    F = np.asarray(triangles, dtype=np.int64)
    S = sp.csr_matrix(landmarks)
    h = Surface(x, F).edge_length()  # unit mean edge length: the scale the constants are applied at
    m_target = np.asarray(landmark_targets, dtype=np.float64) / h
    StS = (S.T @ S).tocsc()
    out = DeformResult(x)
    n = len(x)
    for it in range(schedule.iterations):
        k_s, k_b, k_m, k_c = schedule.weights(it)
        xs = x / h
        K = -igl.cotmatrix(xs, F)
        mass = igl.massmatrix(xs, F, igl.MASSMATRIX_TYPE_VORONOI).diagonal()
        mass = np.where(mass > 1e-12, mass, max(float(mass.mean()), 1e-12))
        A = k_s * K + k_b * (K @ sp.diags(1.0 / mass) @ K) + k_m * StS
        b = k_m * (S.T @ (m_target - S @ xs))
        p, ok, dist = closest_targets(x, F, target, max_angle)
        if k_c > 0:
            c = ok.astype(np.float64)
            A = A + k_c * sp.diags(c)
            b = b + k_c * c[:, None] * (p / h - xs)
        # a vanishing pull towards no motion keeps parts with no landmark and no match solvable
        A = (A + sp.identity(n) * (1e-9 * max(float(A.diagonal().mean()), 1e-12))).tocsc()
        d = splu(A).solve(np.ascontiguousarray(b))
        x = (xs + d) * h
        p, ok, dist = closest_targets(x, F, target, max_angle)
        out.rms.append(float(np.sqrt(np.mean(dist[ok] ** 2))) if ok.any() else float("nan"))
        out.matched.append(float(ok.mean()))
        out.landmark_error.append(float(np.sqrt(np.mean(np.sum((S @ x - landmark_targets) ** 2, axis=1))))
                                  if S.shape[0] else 0.0)
        if progress is not None:
            progress(it + 1, schedule.iterations)
    out.vertices = x
    return out
