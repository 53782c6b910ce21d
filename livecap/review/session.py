"""One take under review: its solve, the edit history, pins and keys. No web code here.

The review page and ``livecap pose`` both work through this object; the server only translates
JSON to these calls.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from livecap.calibration.profile import Profile
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.core.take import Take
from solvers.keyreduce import Keys, KeySettings, evaluate_keys, reduce_curves, shared_keys
from solvers.manipulation import DirectManipulation, ManipulationSettings
from solvers.movement import Edit

EDIT_PAD = 32  # frames of context each side of an edit's range for solvers that smooth the markers


@dataclass
class Change:
    """One undoable change: rows a..b of the weights before and after."""

    a: int
    b: int
    before: np.ndarray
    after: np.ndarray


@dataclass
class Pin:
    """A point of the face held at ``goal`` (mm, rig frame): a vertex, or a marker site by label."""

    goal: np.ndarray
    vertex: int | None = None
    marker: str | None = None

    def key(self) -> tuple:
        return ("v", self.vertex) if self.marker is None else ("m", self.marker)


def pin_rows(rig: Rig, layout: MarkerLayout | None, pins: list[Pin]) -> sp.csr_matrix:
    """Sampling rows (P x V): each pin as a vertex or its marker's barycentric site."""
    rows = []
    S = None
    for p in pins:
        if p.marker is not None:
            if layout is None or p.marker not in layout.labels:
                raise ValueError(f"pin: unknown marker {p.marker!r}")
            if S is None:
                S = layout.sampling_matrix(rig.n_vertices)
            rows.append(S[layout.labels.index(p.marker)])
        else:
            if p.vertex is None or not 0 <= int(p.vertex) < rig.n_vertices:
                raise ValueError(f"pin: vertex {p.vertex} is not in 0..{rig.n_vertices - 1}")
            rows.append(sp.csr_matrix(([1.0], ([0], [int(p.vertex)])), shape=(1, rig.n_vertices)))
    return sp.vstack(rows).tocsr()


def manipulator(rig: Rig, layout: MarkerLayout | None, pins: list[Pin],
                settings: ManipulationSettings | None = None) -> DirectManipulation:
    """The prepared pin solver for these pinned points (the rig's linear part, Lewis & Anjyo 2010)."""
    if not pins:
        raise ValueError("pose: no pins given")
    S = pin_rows(rig, layout, pins)
    rest = S @ rig.neutral
    deltas = np.stack([S @ d for d in rig.deltas])
    return DirectManipulation(rest, deltas, rig.lower, rig.upper, settings)


@dataclass
class ReviewSession:
    rig: Rig
    layout: MarkerLayout
    profile: Profile
    take: Take
    weights: np.ndarray  # T x m, profile.names order
    targets: np.ndarray  # T x n x 3 stabilised displacements
    valid: np.ndarray
    rotation: np.ndarray  # T x 4 (x, y, z, w)
    translation: np.ndarray  # T x 3
    editor: object  # anything with edit(W, edits, targets, valid) (livecap edit's movement solver)
    truth: np.ndarray | None = None
    pull: float = 1.0
    undo_stack: list[Change] = field(default_factory=list)
    redo_stack: list[Change] = field(default_factory=list)
    _pins: dict = field(default_factory=dict)
    _keys_cache: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.names = list(self.profile.names)
        self.marker_rig = self.layout.marker_rig(self.rig)
        self.times = np.arange(self.n_frames) / self.take.rate

    @property
    def n_frames(self) -> int:
        return len(self.weights)

    def rig_weights(self, w: np.ndarray) -> np.ndarray:
        """Profile-ordered weights in the rig's shape order."""
        out = np.zeros(self.rig.n_shapes)
        out[[self.rig.index(n) for n in self.names]] = w
        return out

    def residuals(self) -> np.ndarray:
        """Per-frame RMS (mm) over the valid markers of solve vs stabilised marker movement."""
        pred = (self.weights @ self.profile.basis.T).reshape(self.n_frames, -1, 3)
        err = np.sum((pred - self.targets) ** 2, axis=2)
        n = np.maximum(self.valid.sum(1), 1)
        return np.sqrt(np.sum(np.where(self.valid, err, 0.0), axis=1) / n)

    def frame(self, i: int) -> dict:
        """What the page draws at frame i: weights, head pose, observed markers and fitted sites."""
        i = self._check_frame(i)
        w = self.weights[i]
        sites = self.marker_rig.evaluate(self.rig_weights(w))
        observed = self.profile.target_sites + self.targets[i]
        return {"frame": i, "weights": w.tolist(), "rotation": self.rotation[i].tolist(),
                "translation": self.translation[i].tolist(), "sites": sites.tolist(),
                "observed": observed.tolist(), "valid": self.valid[i].tolist(),
                "truth": None if self.truth is None else self.truth[i].tolist()}

    def _check_frame(self, i: int) -> int:
        i = int(i)
        if not 0 <= i < self.n_frames:
            raise ValueError(f"frame {i} is outside the take (0..{self.n_frames - 1})")
        return i

    # ------------------------------------------------------------------ edits
    def edit(self, frame: int, values: dict[str, float], a: int, b: int) -> tuple[Change, float]:
        """Spacetime edit (Seol §6): set ``values`` at ``frame``, re-solve frames a..b. Returns the change
        and the solver's time in seconds."""
        k = self._check_frame(frame)
        a, b = max(0, int(a)), min(self.n_frames - 1, int(b))
        if not a <= k <= b:
            raise ValueError(f"edit range [{a}, {b}] must contain frame {k}")
        index = {n: j for j, n in enumerate(self.names)}
        unknown = [n for n in values if n not in index]
        if unknown:
            raise ValueError(f"edit: unknown shapes {unknown[:5]}")
        # the edit changes only a..b (both ends fixed): solve on a window around it, padded so the source
        # marker smoothing of the robust solve sees the same neighbourhood as on the whole take
        pad = EDIT_PAD if hasattr(self.editor, "smooth") else 0
        lo, hi = max(0, a - pad), min(self.n_frames, b + 1 + pad)
        edit = Edit(k - lo, {index[n]: float(v) for n, v in values.items()}, (a - lo, b - lo))
        start = time.perf_counter()
        E = self.editor.edit(self.weights[lo:hi].copy(), [edit], self.targets[lo:hi], self.valid[lo:hi])
        elapsed = time.perf_counter() - start
        change = Change(a, b, self.weights[a:b + 1].copy(), E[a - lo:b + 1 - lo].copy())
        self._apply(change, change.after)
        self.undo_stack.append(change)
        self.redo_stack.clear()
        return change, elapsed

    def _apply(self, change: Change, rows: np.ndarray) -> None:
        self.weights[change.a:change.b + 1] = rows

    def undo(self) -> Change | None:
        if not self.undo_stack:
            return None
        c = self.undo_stack.pop()
        self._apply(c, c.before)
        self.redo_stack.append(c)
        return c

    def redo(self) -> Change | None:
        if not self.redo_stack:
            return None
        c = self.redo_stack.pop()
        self._apply(c, c.after)
        self.undo_stack.append(c)
        return c

    # ------------------------------------------------------------------ direct manipulation
    def pose(self, frame: int, pins: list[Pin]) -> tuple[np.ndarray, float]:
        """Weights (profile order) that put the pins at their goals, pulled to frame's current weights;
        also the solve time in seconds (the pin set's preparation is cached and not counted)."""
        i = self._check_frame(frame)
        key = tuple(p.key() for p in pins)
        if key not in self._pins:
            if len(self._pins) > 64:
                self._pins.clear()
            self._pins[key] = manipulator(self.rig, self.layout, pins, ManipulationSettings(pull=self.pull))
        dm = self._pins[key]
        order = [self.rig.index(n) for n in self.names]
        current = self.rig_weights(self.weights[i])
        goals = np.array([p.goal for p in pins], dtype=np.float64)
        start = time.perf_counter()
        w = dm.step(goals, current)
        return w[order], time.perf_counter() - start

    # ------------------------------------------------------------------ keys
    def keys(self, max_error: float) -> list[Keys]:
        if not max_error > 0:
            raise ValueError(f"max_error must be > 0, not {max_error}")
        version = (len(self.undo_stack), len(self.redo_stack), id(self.undo_stack[-1]) if self.undo_stack else 0)
        if self._keys_cache.get("key") != (max_error, version):
            self._keys_cache = {"key": (max_error, version),
                                "keys": reduce_curves(self.times, self.weights, KeySettings(max_error))}
        return self._keys_cache["keys"]

    def keys_report(self, max_error: float) -> dict:
        keys = self.keys(max_error)
        err = [float(np.max(np.abs(evaluate_keys(k, self.times) - self.weights[:, j]))) for j, k in enumerate(keys)]
        count = sum(len(k.frames) for k in keys)
        return {"max_error": max_error, "keys": count, "fraction": count / self.weights.size,
                "worst": max(err), "shapes": {n: {"frames": k.frames.tolist(), "values": k.values.tolist(),
                                                  "in": k.in_tangents.tolist(), "out": k.out_tangents.tolist(),
                                                  "error": e}
                                              for n, k, e in zip(self.names, keys, err, strict=True)}}

    def keys_csv(self, max_error: float) -> str:
        lines = ["shape,frame,time,value,in_tangent,out_tangent"]
        f0 = self.take.first_frame
        for n, k in zip(self.names, self.keys(max_error), strict=True):
            for f, v, a, b in zip(k.frames, k.values, k.in_tangents, k.out_tangents, strict=True):
                lines.append(f"{n},{f + f0},{self.times[f]:.6f},{v:.6g},{a:.6g},{b:.6g}")
        return "\n".join(lines) + "\n"

    def keys_glb(self, max_error: float) -> bytes:
        from transport.gltf import glb_bytes

        frames, values, ins, outs = shared_keys(self.keys(max_error), self.times)
        return glb_bytes(self.rig, self.names, self.times[frames], values, name="keys", tangents=(ins, outs))

    def weights_csv(self) -> str:
        head = "frame,time," + ",".join(self.names)
        f0 = self.take.first_frame
        rows = [f"{f0 + i},{self.times[i]:.6f}," + ",".join(f"{x:.6g}" for x in w) for i, w in enumerate(self.weights)]
        return "\n".join([head, *rows]) + "\n"
