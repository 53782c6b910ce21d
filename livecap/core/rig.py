"""The target blendshape rig (Lewis et al. 2014, §3).

Delta formulation (Lewis §3.1, Eq. 4): ``face = neutral + sum_k w_k d_k``, extended by

* in-between shapes (Lewis §3.2): sculpts at intermediate weights of one shape, giving a
  piecewise-linear path through them; stored as the residual against the straight line
  ``D_i - w_i d_k`` carried by a hat function, so weights outside [0, 1] stay linear;
* combination (corrective) shapes (Lewis §3.3): added with the product of two or three weights.

All geometry is held in millimetres; units are converted when a rig is loaded.
"""

from __future__ import annotations

import json
import logging
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from livecap.core.objfile import read_obj, write_obj
from livecap.core.units import to_mm

log = logging.getLogger(__name__)

INBETWEEN_SEP = "@"
COMBINATION_SEP = "+"


class RigError(ValueError):
    """A rig that cannot be built or loaded; the message says which file or shape."""


@dataclass(frozen=True)
class InBetween:
    """Sculpt of shape ``shape`` at weight ``weight`` (0 < weight < 1), as a residual field."""

    shape: int
    weight: float
    left: float
    right: float
    residual: np.ndarray  # V x 3: D_i - weight * d_shape

    def hat(self, w: np.ndarray) -> np.ndarray:
        up = (w - self.left) / (self.weight - self.left)
        down = (self.right - w) / (self.right - self.weight)
        return np.clip(np.minimum(up, down), 0.0, None)


@dataclass(frozen=True)
class Corrective:
    """Combination shape added with the product of the weights of ``shapes`` (2 or 3 of them)."""

    shapes: tuple[int, ...]
    delta: np.ndarray  # V x 3, the increment over the sum of its parts


@dataclass
class Rig:
    neutral: np.ndarray
    triangles: np.ndarray
    names: list[str]
    deltas: np.ndarray
    lower: np.ndarray = field(default=None)  # type: ignore[assignment]
    upper: np.ndarray = field(default=None)  # type: ignore[assignment]
    inbetweens: list[InBetween] = field(default_factory=list)
    correctives: list[Corrective] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.neutral = np.asarray(self.neutral, dtype=np.float64)
        self.triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)
        self.deltas = np.asarray(self.deltas, dtype=np.float64).reshape(len(self.names), -1, 3)
        m = len(self.names)
        self.lower = np.zeros(m) if self.lower is None else np.asarray(self.lower, dtype=np.float64)
        self.upper = np.ones(m) if self.upper is None else np.asarray(self.upper, dtype=np.float64)
        if len(set(self.names)) != m:
            raise RigError("shape names must be unique")
        if self.neutral.ndim != 2 or self.neutral.shape[1] != 3:
            raise RigError(f"neutral must be V x 3, got {self.neutral.shape}")
        if self.deltas.shape[1] != self.neutral.shape[0]:
            raise RigError(
                f"deltas have {self.deltas.shape[1]} vertices, neutral has {self.neutral.shape[0]}"
            )
        if not (np.isfinite(self.neutral).all() and np.isfinite(self.deltas).all()):
            raise RigError("rig has NaN or infinite vertex coordinates")
        if self.lower.shape != (m,) or self.upper.shape != (m,) or np.any(self.lower > self.upper):
            raise RigError("weight limits must be one [lower <= upper] pair per shape")

    # ------------------------------------------------------------------ size
    @property
    def n_shapes(self) -> int:
        return len(self.names)

    @property
    def n_vertices(self) -> int:
        return self.neutral.shape[0]

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise RigError(f"rig has no shape named {name!r}") from None

    @property
    def is_linear(self) -> bool:
        return not self.inbetweens and not self.correctives

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, weights: np.ndarray) -> np.ndarray:
        """Vertices for weights ``(m,)`` -> ``(V, 3)`` or ``(T, m)`` -> ``(T, V, 3)``."""
        w = np.asarray(weights, dtype=np.float64)
        single = w.ndim == 1
        w = np.atleast_2d(w)
        if w.shape[1] != self.n_shapes:
            raise RigError(f"expected {self.n_shapes} weights, got {w.shape[1]}")
        flat = self.deltas.reshape(self.n_shapes, -1)
        out = w @ flat
        for ib in self.inbetweens:
            out += np.outer(ib.hat(w[:, ib.shape]), ib.residual.ravel())
        for c in self.correctives:
            out += np.outer(np.prod(w[:, list(c.shapes)], axis=1), c.delta.ravel())
        out = out.reshape(len(w), -1, 3) + self.neutral
        return out[0] if single else out

    # ------------------------------------------------------------------ sub-rigs
    def sample(self, matrix) -> Rig:
        """The rig seen through a linear sampling of its vertices (n x V, e.g. marker sites).

        Every part of the rig is linear in vertex positions, so sampling commutes with evaluation.
        """
        def s(a: np.ndarray) -> np.ndarray:
            return np.asarray(matrix @ a)

        return Rig(
            neutral=s(self.neutral),
            triangles=np.zeros((0, 3), dtype=np.int64),
            names=list(self.names),
            deltas=np.stack([s(d) for d in self.deltas]) if self.n_shapes else np.zeros((0, matrix.shape[0], 3)),
            lower=self.lower.copy(),
            upper=self.upper.copy(),
            inbetweens=[InBetween(i.shape, i.weight, i.left, i.right, s(i.residual)) for i in self.inbetweens],
            correctives=[Corrective(c.shapes, s(c.delta)) for c in self.correctives],
        )

    def with_limits(self, limits: Mapping[str, Sequence[float]]) -> Rig:
        lo, hi = self.lower.copy(), self.upper.copy()
        for name, (a, b) in limits.items():
            k = self.index(name)
            lo[k], hi[k] = a, b
        return Rig(self.neutral, self.triangles, self.names, self.deltas, lo, hi,
                   self.inbetweens, self.correctives)

    # ------------------------------------------------------------------ whole-face form
    def whole_face(self) -> dict[str, np.ndarray]:
        """Each sculpt as a whole face (Lewis §7.3): shapes, ``name@w`` in-betweens, ``a+b`` combos."""
        out: dict[str, np.ndarray] = {}
        for k, name in enumerate(self.names):
            out[name] = self.neutral + self.deltas[k]
        for ib in self.inbetweens:
            w = np.zeros(self.n_shapes)
            w[ib.shape] = ib.weight
            out[f"{self.names[ib.shape]}{INBETWEEN_SEP}{ib.weight:g}"] = self.evaluate(w)
        for c in self.correctives:
            w = np.zeros(self.n_shapes)
            w[list(c.shapes)] = 1.0
            out[COMBINATION_SEP.join(self.names[i] for i in c.shapes)] = self.evaluate(w)
        return out

    @classmethod
    def from_whole_face(
        cls,
        neutral: np.ndarray,
        triangles: np.ndarray,
        faces: Mapping[str, np.ndarray],
        limits: Mapping[str, Sequence[float]] | None = None,
    ) -> Rig:
        """Build a delta rig from whole-face sculpts named as in :meth:`whole_face`."""
        neutral = np.asarray(neutral, dtype=np.float64)
        primary = {k: v for k, v in faces.items() if INBETWEEN_SEP not in k and COMBINATION_SEP not in k}
        names = sorted(primary)
        deltas = np.array([np.asarray(primary[n]) - neutral for n in names]).reshape(len(names), -1, 3)
        rig = cls(neutral, triangles, names, deltas)

        by_shape: dict[int, list[tuple[float, np.ndarray]]] = {}
        for key, face in faces.items():
            if INBETWEEN_SEP not in key:
                continue
            base, _, wtxt = key.partition(INBETWEEN_SEP)
            try:
                w = float(wtxt)
            except ValueError:
                raise RigError(f"in-between {key!r}: weight after '@' is not a number") from None
            if not 0.0 < w < 1.0:
                raise RigError(f"in-between {key!r}: weight must lie strictly between 0 and 1")
            by_shape.setdefault(rig.index(base), []).append((w, np.asarray(face) - neutral))
        for k, items in by_shape.items():
            items.sort(key=lambda t: t[0])
            knots = [0.0] + [w for w, _ in items] + [1.0]
            for j, (w, disp) in enumerate(items, 1):
                rig.inbetweens.append(InBetween(k, w, knots[j - 1], knots[j + 1], disp - w * rig.deltas[k]))

        combos = []
        for key, face in faces.items():
            if COMBINATION_SEP not in key:
                continue
            members = tuple(rig.index(n) for n in key.split(COMBINATION_SEP))
            if not 2 <= len(members) <= 3 or len(set(members)) != len(members):
                raise RigError(f"combination {key!r} must name 2 or 3 distinct shapes")
            combos.append((members, np.asarray(face)))
        for members, face in sorted(combos, key=lambda t: len(t[0])):
            w = np.zeros(rig.n_shapes)
            w[list(members)] = 1.0
            rig.correctives.append(Corrective(members, face - rig.evaluate(w)))
        return rig.with_limits(limits or {})

    # ------------------------------------------------------------------ files
    @classmethod
    def load(cls, path: str | Path, units: str | None = None) -> Rig:
        """Load an OBJ folder or a ``.npz`` written by :meth:`save`."""
        path = Path(path)
        if not path.exists():
            raise RigError(f"{path}: no such rig (expected an OBJ folder or a .npz file)")
        if path.is_dir():
            return cls._load_obj_folder(path, units)
        if path.suffix == ".npz":
            return cls._load_npz(path)
        raise RigError(f"{path}: not a rig (expected an OBJ folder or a .npz file)")

    @classmethod
    def _load_obj_folder(cls, folder: Path, units: str | None) -> Rig:
        neutral_path = folder / "neutral.obj"
        if not neutral_path.exists():
            raise RigError(f"{folder}: rig folder has no neutral.obj")
        meta = _folder_metadata(folder)
        units = units or meta.get("units")
        if units is None:
            log.warning("%s: no units in rig.json or markers.json; assuming millimetres", folder)
            units = "mm"
        scale = to_mm(1.0, units)
        neutral, tris = read_obj(neutral_path)
        faces: dict[str, np.ndarray] = {}
        for p in sorted(folder.glob("*.obj")):
            if p.name == "neutral.obj":
                continue
            v, f = read_obj(p)
            if v.shape != neutral.shape:
                raise RigError(f"{p}: {len(v)} vertices, neutral.obj has {len(neutral)} (mismatched topology)")
            if len(f) and (f.shape != tris.shape or not np.array_equal(f, tris)):
                raise RigError(f"{p}: faces differ from neutral.obj (mismatched topology)")
            if not np.isfinite(v).all():
                raise RigError(f"{p}: NaN or infinite vertex coordinates")
            faces[p.stem] = v * scale
        if not np.isfinite(neutral).all():
            raise RigError(f"{neutral_path}: NaN or infinite vertex coordinates")
        try:
            return cls.from_whole_face(neutral * scale, tris, faces, meta.get("limits"))
        except RigError as exc:
            raise RigError(f"{folder}: {exc}") from None

    def save_obj_folder(self, folder: str | Path) -> None:
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        write_obj(folder / "neutral.obj", self.neutral, self.triangles, "livecap rig, millimetres")
        for name, face in self.whole_face().items():
            write_obj(folder / f"{name}.obj", face, self.triangles)
        limits = {n: [float(a), float(b)] for n, a, b in zip(self.names, self.lower, self.upper, strict=True)
                  if (a, b) != (0.0, 1.0)}
        (folder / "rig.json").write_text(json.dumps({"units": "mm", "limits": limits}, indent=1))

    def save(self, path: str | Path) -> None:
        """Write the rig's own ``.npz`` (float32 geometry, millimetres)."""
        f32 = np.float32
        arrays = {
            "neutral": self.neutral.astype(f32),
            "triangles": self.triangles.astype(np.int32),
            "names": np.array(self.names),
            "deltas": self.deltas.astype(f32),
            "lower": self.lower,
            "upper": self.upper,
            "ib_shape": np.array([i.shape for i in self.inbetweens], dtype=np.int32),
            "ib_knots": np.array([(i.left, i.weight, i.right) for i in self.inbetweens]).reshape(-1, 3),
            "ib_residual": np.array([i.residual for i in self.inbetweens], dtype=f32).reshape(-1, self.n_vertices, 3),
            "co_shapes": np.array([c.shapes + (-1,) * (3 - len(c.shapes)) for c in self.correctives],
                                  dtype=np.int32).reshape(-1, 3),
            "co_delta": np.array([c.delta for c in self.correctives], dtype=f32).reshape(-1, self.n_vertices, 3),
        }
        np.savez_compressed(path, **arrays)

    @classmethod
    def _load_npz(cls, path: Path) -> Rig:
        try:
            z = np.load(path, allow_pickle=False)
            ibs = [InBetween(int(s), float(k[1]), float(k[0]), float(k[2]), r.astype(np.float64))
                   for s, k, r in zip(z["ib_shape"], z["ib_knots"], z["ib_residual"], strict=True)]
            cos = [Corrective(tuple(int(i) for i in s if i >= 0), d.astype(np.float64))
                   for s, d in zip(z["co_shapes"], z["co_delta"], strict=True)]
            return cls(z["neutral"], z["triangles"], [str(n) for n in z["names"]], z["deltas"],
                       z["lower"], z["upper"], ibs, cos)
        except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise RigError(f"{path}: not a livecap rig file ({exc})") from None


def _folder_metadata(folder: Path) -> dict:
    meta: dict = {}
    for name in ("markers.json", "rig.json"):
        p = folder / name
        if p.exists():
            try:
                data = json.loads(p.read_text())
            except json.JSONDecodeError as exc:
                raise RigError(f"{p}: invalid JSON ({exc})") from None
            meta.update({k: data[k] for k in ("units", "limits") if k in data})
    return meta
