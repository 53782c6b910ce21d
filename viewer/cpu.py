"""CPU deformation baseline: ``Rig.evaluate`` plus numpy vertex normals, uploaded per frame."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from livecap.core.rig import Rig


class CpuDeformer:
    """Deformed positions and area-weighted normals (float32) for the CPU-upload path."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        t = rig.triangles
        rows = t.ravel()
        cols = np.repeat(np.arange(len(t)), 3)
        self._incidence = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(rig.n_vertices, len(t)))

    def __call__(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = self.rig.evaluate(weights)
        t = self.rig.triangles
        a = p[t[:, 0]]
        fn = np.cross(p[t[:, 1]] - a, p[t[:, 2]] - a)
        n = self._incidence @ fn
        length = np.linalg.norm(n, axis=1, keepdims=True)
        n = np.where(length > 0, n / np.maximum(length, 1e-300), [0.0, 0.0, 1.0])
        return p.astype(np.float32), n.astype(np.float32)
