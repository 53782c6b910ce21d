"""Marker layout: which rig surface point each labelled marker sits on.

A marker is bound to a vertex or to a point inside a triangle (barycentric), so its site is a
fixed linear combination of vertices; the marker-space basis B (3n x m) is the rig sampled
there (the "corresponding source/target points" of Seol et al. 2012, §3).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from livecap.core.rig import Rig
from livecap.core.units import MM_PER_UNIT


class LayoutError(ValueError):
    """A markers.json that cannot be used; the message names the file and the marker."""


@dataclass
class MarkerLayout:
    labels: list[str]
    vertices: np.ndarray  # n x 3 vertex indices of the triangle (or the vertex repeated)
    barycentric: np.ndarray  # n x 3
    stable: np.ndarray  # n bool
    units: str = "mm"

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.int64).reshape(-1, 3)
        self.barycentric = np.asarray(self.barycentric, dtype=np.float64).reshape(-1, 3)
        self.stable = np.asarray(self.stable, dtype=bool)
        n = len(self.labels)
        if len(set(self.labels)) != n:
            raise LayoutError("marker labels must be unique")
        if self.vertices.shape != (n, 3) or self.barycentric.shape != (n, 3) or self.stable.shape != (n,):
            raise LayoutError("one vertex binding and one stable flag per marker")

    @property
    def n_markers(self) -> int:
        return len(self.labels)

    @classmethod
    def from_vertices(cls, labels: list[str], vertices, stable, units: str = "mm") -> MarkerLayout:
        v = np.asarray(vertices, dtype=np.int64)
        bary = np.tile([1.0, 0.0, 0.0], (len(v), 1))
        return cls(list(labels), np.stack([v, v, v], axis=1), bary, stable, units)

    # ------------------------------------------------------------------ files
    @classmethod
    def load(cls, path: str | Path, rig: Rig | None = None) -> MarkerLayout:
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:  # ValueError: JSON and UTF-8 decode errors
            raise LayoutError(f"{path}: cannot read marker layout ({exc})") from None
        if not isinstance(data, dict) or not isinstance(data.get("markers", []), list):
            raise LayoutError(f"{path}: a marker layout is a JSON object with a \"markers\" list")
        units = data.get("units", "mm")
        if units not in MM_PER_UNIT:
            raise LayoutError(f"{path}: unknown units {units!r}")
        labels, verts, bary, stable = [], [], [], []
        for i, m in enumerate(data.get("markers", [])):
            if not isinstance(m, dict):
                raise LayoutError(f"{path}: marker #{i} is not a JSON object")
            where = f"{path}: marker #{i} ({m.get('label', '?')})"
            if "label" not in m:
                raise LayoutError(f"{where}: no label")
            if "vertex" in m:
                v = _index(m["vertex"], where, "vertex")
                verts.append((v, v, v))
                bary.append((1.0, 0.0, 0.0))
            elif "triangle" in m and "barycentric" in m:
                if rig is None:
                    raise LayoutError(f"{where}: triangle bindings need the rig to resolve")
                t = _index(m["triangle"], where, "triangle")
                if not 0 <= t < len(rig.triangles):
                    raise LayoutError(f"{where}: triangle {t} out of range")
                try:
                    b = np.asarray(m["barycentric"], dtype=float)
                except (TypeError, ValueError):
                    raise LayoutError(f"{where}: barycentric must be 3 numbers summing to 1") from None
                if b.shape != (3,) or abs(b.sum() - 1.0) > 1e-6:
                    raise LayoutError(f"{where}: barycentric must be 3 numbers summing to 1")
                verts.append(tuple(rig.triangles[t]))
                bary.append(tuple(b))
            else:
                raise LayoutError(f"{where}: needs 'vertex' or 'triangle' + 'barycentric'")
            labels.append(str(m["label"]))
            stable.append(bool(m.get("stable", False)))
        if not labels:
            raise LayoutError(f"{path}: no markers")
        dups = sorted({lab for lab in labels if labels.count(lab) > 1})
        if dups:
            raise LayoutError(f"{path}: marker labels {dups[:5]} appear more than once")
        layout = cls(labels, verts, bary, stable, units)
        same = layout.coincident()
        if same:
            raise LayoutError(f"{path}: markers {' and '.join(same[0])} are bound to the same rig point"
                              + (f" (and {len(same) - 1} more pairs)" if len(same) > 1 else "")
                              + "; every marker needs its own site")
        if rig is not None:
            layout.check(rig, str(path))
        return layout

    def coincident(self) -> list[tuple[str, str]]:
        """Pairs of markers bound to the same rig point (same vertex, or same triangle and barycentric):
        their sites coincide, so the proportion warp cannot map them to two actor markers."""
        seen: dict[tuple, str] = {}
        out = []
        for lab, v, b in zip(self.labels, self.vertices, self.barycentric, strict=True):
            weights: dict[int, float] = {}
            for i, w in zip(v.tolist(), b.tolist(), strict=True):
                weights[i] = weights.get(i, 0.0) + w
            key = tuple(sorted((i, round(w, 9)) for i, w in weights.items() if abs(w) > 1e-12))
            if key in seen:
                out.append((seen[key], lab))
            else:
                seen[key] = lab
        return out

    def save(self, path: str | Path, rig: Rig | None = None, extra: dict[str, dict] | None = None) -> None:
        """Write markers.json; triangle bindings need the ``rig`` (their triangle index); ``extra`` adds
        per-label keys (a binding's report) that :meth:`load` ignores."""
        Path(path).write_text(self.to_json(rig, extra, where=str(path)))

    def to_json(self, rig: Rig | None = None, extra: dict[str, dict] | None = None, where: str = "layout") -> str:
        """The markers.json text :meth:`save` writes."""
        tri_index = {} if rig is None else {tuple(t): i for i, t in enumerate(np.asarray(rig.triangles).tolist())}
        markers = []
        for lab, v, b, s in zip(self.labels, self.vertices, self.barycentric, self.stable, strict=True):
            entry: dict = {"label": lab}
            if b[0] == 1.0 and v[0] == v[1] == v[2]:
                entry["vertex"] = int(v[0])
            elif tuple(int(i) for i in v) in tri_index:
                entry["triangle"] = tri_index[tuple(int(i) for i in v)]
                entry["barycentric"] = [float(x) for x in b]
            else:
                raise LayoutError(f"{where}: marker {lab} is bound inside a triangle; saving it needs the rig")
            entry["stable"] = bool(s)
            entry.update((extra or {}).get(lab, {}))
            markers.append(entry)
        return json.dumps({"units": self.units, "markers": markers}, indent=1)

    def check(self, rig: Rig, where: str = "layout") -> None:
        if self.vertices.max() >= rig.n_vertices or self.vertices.min() < 0:
            bad = [lab for lab, v in zip(self.labels, self.vertices, strict=True)
                   if v.max() >= rig.n_vertices or v.min() < 0]
            raise LayoutError(f"{where}: markers {bad[:5]} bound to vertices outside the rig's 0..{rig.n_vertices - 1}")

    # ------------------------------------------------------------------ sampling the rig
    def sampling_matrix(self, n_vertices: int) -> sp.csr_matrix:
        """n x V sparse matrix taking rig vertices to marker sites."""
        n = self.n_markers
        rows = np.repeat(np.arange(n), 3)
        return sp.csr_matrix((self.barycentric.ravel(), (rows, self.vertices.ravel())), shape=(n, n_vertices))

    def marker_rig(self, rig: Rig) -> Rig:
        """The rig restricted to the marker sites: evaluates sites for any weights, cheaply."""
        self.check(rig)
        return rig.sample(self.sampling_matrix(rig.n_vertices))

    def basis(self, rig: Rig) -> np.ndarray:
        """Marker-space basis B (3n x m), rows ordered x0 y0 z0 x1 ...; linear part of the rig."""
        d = self.marker_rig(rig).deltas
        return d.reshape(rig.n_shapes, -1).T.copy()

    def stable_labels(self) -> list[str]:
        return [lab for lab, s in zip(self.labels, self.stable, strict=True) if s]


def _index(value, where: str, what: str) -> int:
    """A non-negative integer index from JSON, or a LayoutError naming the marker."""
    if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value) or value < 0:
        raise LayoutError(f"{where}: {what} must be a non-negative integer index, got {value!r}")
    return int(value)
