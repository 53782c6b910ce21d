"""Deformation transfer between two meshes of one topology (Sumner & Popović 2004; Xiang et al. 2008 §3.3).

A source expression is encoded per triangle as the affine map ``T_i = V'_i V_i^-1`` (Xiang Eq. 6-8),
``V_i = [v2 - v1, v3 - v1, v4 - v1]`` with the fourth vertex ``v4 = v1 + n / sqrt(|n|)`` off the
triangle along its normal (Eq. 7). The target expression minimises ``sum_i |T_i^g - T_i^f|_F^2``
(Eq. 9) over the target's vertices and fourth vertices: a sparse linear least-squares problem
whose matrix depends only on the target neutral, so ``A^T A`` is factored once (SuperLU) and every
expression, in-between and corrective costs three back-substitutions.

The energy sees only differences of vertices, so each connected piece of the mesh has a free
translation. It is removed by pinning one vertex per piece while solving and then fixed so the
piece's mean displacement equals the mean of the source displacement carried over by topology
(the only translation a per-triangle encoding cannot know; e.g. jawOpen keeps the skull still).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from livecap.transfer.surface import adjacency


class DegenerateMeshError(ValueError):
    """A mesh whose triangles cannot carry deformation gradients."""


def frames(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Per-triangle 3 x 3 frames ``[v2 - v1, v3 - v1, v4 - v1]`` (Xiang Eq. 7-8), columns are edges."""
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = (v[..., triangles[:, k], :] for k in range(3))
    e1, e2 = b - a, c - a
    n = np.cross(e1, e2)
    ln = np.linalg.norm(n, axis=-1, keepdims=True)
    e3 = np.divide(n, np.sqrt(ln), out=np.zeros_like(n), where=ln > 0)
    return np.stack([e1, e2, e3], axis=-1)


def deformation_gradients(neutral: np.ndarray, deformed: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``T_i = V'_i V_i^-1`` for every triangle (Xiang Eq. 8); ``deformed`` may be (..., V, 3)."""
    inv = np.linalg.inv(frames(neutral, triangles))
    return frames(deformed, triangles) @ inv


class DeformationTransfer:
    """Transfer source deformations onto a target of the same topology (Sumner & Popović 2004 §3-4).

    The constructor builds and factors the normal equations of the target; :meth:`transfer`
    solves for any number of source poses.
    """

    def __init__(self, source_neutral: np.ndarray, target_neutral: np.ndarray, triangles: np.ndarray,
                 min_area: float = 1e-12) -> None:
        self.source_neutral = np.asarray(source_neutral, dtype=np.float64)
        self.target_neutral = np.asarray(target_neutral, dtype=np.float64)
        self.triangles = np.asarray(triangles, dtype=np.int64)
        n, F = len(self.target_neutral), self.triangles
        scale = float(np.ptp(self.target_neutral, axis=0).max()) or 1.0
        # triangles degenerate in either neutral carry no gradient
        def areas(v):
            return 0.5 * np.linalg.norm(np.cross(v[F[:, 1]] - v[F[:, 0]], v[F[:, 2]] - v[F[:, 0]]), axis=1)
        floor = min_area * scale ** 2
        good = (areas(self.source_neutral) > floor) & (areas(self.target_neutral) > floor)
        if not good.any():
            raise DegenerateMeshError("every triangle is degenerate")
        self.good = good
        tri = F[good]
        m = len(tri)
        self._source_inv = np.linalg.inv(frames(self.source_neutral, tri))
        W = np.linalg.inv(frames(self.target_neutral, tri))  # (m, 3, 3)
        # row (i, j) of T_f = V' W for one coordinate: sum_k V'[k] W[k, j], V' = [x_b - x_a, x_c - x_a, x_4 - x_a]
        rows = np.repeat(np.arange(3 * m), 4)
        cols = np.stack([tri[:, 0], tri[:, 1], tri[:, 2], n + np.arange(m)], axis=1)  # unknowns: vertices, then v4s
        cols = np.repeat(cols, 3, axis=0)  # (3m, 4)
        Wt = np.transpose(W, (0, 2, 1)).reshape(-1, 3)  # row (i, j) -> W[i, :, j]
        vals = np.concatenate([-Wt.sum(1, keepdims=True), Wt], axis=1)
        A = sp.csr_matrix((vals.ravel(), (rows, cols.ravel())), shape=(3 * m, n + m))
        # pin one vertex per connected piece (and every vertex no good triangle uses)
        used = np.zeros(n, dtype=bool)
        used[tri.ravel()] = True
        n_pieces, piece = connected_components(adjacency(tri, n), directed=False)
        pinned = ~used
        for k in range(n_pieces):
            members = np.where((piece == k) & used)[0]
            if len(members):
                pinned[members[0]] = True
        self._piece, self._pinned, self._used = piece, pinned, used
        free = np.concatenate([~pinned, np.ones(m, dtype=bool)])
        self._A = A
        self._Af = A[:, free].tocsc()
        self._Ap = A[:, np.where(~free)[0]].tocsc()
        self._free = free
        self._lu = splu((self._Af.T @ self._Af).tocsc())
        self.n_unknowns = int(free.sum())

    def transfer(self, source_deformed: np.ndarray) -> np.ndarray:
        """Target pose(s) for source pose(s) ``source_deformed`` ((V, 3) or (K, V, 3))."""
        src = np.asarray(source_deformed, dtype=np.float64)
        single = src.ndim == 2
        src = src[None] if single else src
        n = len(self.target_neutral)
        out = np.empty_like(src)
        for k, pose in enumerate(src):
            T = frames(pose, self.triangles[self.good]) @ self._source_inv  # (m, 3, 3)
            # for coordinate r the right-hand side rows (i, j) are T[i, r, j]
            rhs = np.transpose(T, (0, 2, 1)).reshape(-1, 3)  # row (i, j), column r
            naive = self.target_neutral + (pose - self.source_neutral)
            pin = naive[self._pinned]
            x = np.empty((n + len(T), 3))
            x[np.where(~self._free)[0]] = pin
            x[self._free] = self._lu.solve(np.ascontiguousarray(self._Af.T @ (rhs - self._Ap @ pin)))
            verts = x[:n]
            # translation of every piece: mean displacement as carried over by topology
            for p in np.unique(self._piece):
                sel = (self._piece == p) & self._used
                if sel.any():
                    verts[sel] += (naive[sel] - verts[sel]).mean(0)
            out[k] = verts
        return out[0] if single else out
