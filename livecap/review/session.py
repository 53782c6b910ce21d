"""One take under review: its solve, the edit history, pins and keys. No web code here.

The review page and ``livecap pose`` both work through this object; the server only translates
JSON to these calls.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property

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
    """One undoable change: rows a..b of the weights before and after, made by ``client`` (a browser tab)."""

    a: int
    b: int
    before: np.ndarray
    after: np.ndarray
    client: str = ""
    id: int = 0


class EditConflict(ValueError):
    """An undo/redo whose rows were changed since by another client's edit."""


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
    undo_stacks: dict[str, list[Change]] = field(default_factory=dict)  # per client (browser tab)
    redo_stacks: dict[str, list[Change]] = field(default_factory=dict)
    journal: object | None = None  # an EditJournal (livecap.review.journal) once attached
    version: int = 0  # bumped by every change: what cached results are keyed on
    moved_markers: set[str] = field(default_factory=set)  # labels rebound on the page (save markers.json)
    _pins: dict = field(default_factory=dict)
    _keys_cache: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.names = list(self.profile.names)
        self.marker_rig = self.layout.marker_rig(self.rig)
        self.times = np.arange(self.n_frames) / self.take.rate

    @property
    def n_frames(self) -> int:
        return len(self.weights)

    @cached_property
    def _rig_order(self) -> np.ndarray:
        """Each profile shape's index in the rig (looked up once, not per drag message)."""
        return np.array([self.rig.index(n) for n in self.names], dtype=np.intp)

    def rig_weights(self, w: np.ndarray) -> np.ndarray:
        """Profile-ordered weights in the rig's shape order."""
        out = np.zeros(self.rig.n_shapes)
        out[self._rig_order] = w
        return out

    def residuals(self) -> np.ndarray:
        """Per-frame RMS (mm) over the valid markers of solve vs stabilised marker movement."""
        pred = (self.weights @ self.profile.basis.T).reshape(self.n_frames, -1, 3)
        err = np.sum((pred - self.targets) ** 2, axis=2)
        n = np.maximum(self.valid.sum(1), 1)
        return np.sqrt(np.sum(np.where(self.valid, err, 0.0), axis=1) / n)

    def move_marker(self, frame: int, label: str, corners: list[int], point: np.ndarray) -> dict:
        """Rebind a marker where the user dropped it (livecap.review.markers); the drawn sites follow."""
        from livecap.review.markers import move_marker

        out = move_marker(self.layout, self.rig, label, corners, point, self.rig_weights(self.weights[frame]))
        self.marker_rig = self.layout.marker_rig(self.rig)
        self.moved_markers.add(label)
        return out

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
    def edit(self, frame: int, values: dict[str, float], a: int, b: int, client: str = "") -> tuple[Change, float]:
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
        after = E[a - lo:b + 1 - lo]
        if not np.all(np.isfinite(after)):
            raise ValueError(f"edit: the re-solve of frames {a}..{b} is not finite; nothing changed")
        return self._record_edit(a, b, after.copy(), client), elapsed

    def _record_edit(self, a: int, b: int, after: np.ndarray, client: str) -> Change:
        self.version += 1
        change = Change(a, b, self.weights[a:b + 1].copy(), after, client, self.version)
        if self.journal is not None:  # on disk before it is applied or acknowledged
            self.journal.append({"op": "edit", "id": change.id, "client": client, "a": a, "b": b,
                                 "after": after.tolist()})
        self._apply(change, change.after)
        self.undo_stacks.setdefault(client, []).append(change)
        self.redo_stacks.pop(client, None)
        return change

    def _apply(self, change: Change, rows: np.ndarray) -> None:
        self.weights[change.a:change.b + 1] = rows

    def undo(self, client: str = "") -> Change | None:
        """Undo ``client``'s last edit: only its own, and only while its rows are as it left them
        (another tab's later edit over them must be undone first: :class:`EditConflict`)."""
        return self._move(client, self.undo_stacks, self.redo_stacks, "undo")

    def redo(self, client: str = "") -> Change | None:
        return self._move(client, self.redo_stacks, self.undo_stacks, "redo")

    def _move(self, client: str, source: dict, target: dict, op: str) -> Change | None:
        stack = source.get(client)
        if not stack:
            return None
        c = stack[-1]
        now, to = (c.after, c.before) if op == "undo" else (c.before, c.after)
        if not np.array_equal(self.weights[c.a:c.b + 1], now):
            raise EditConflict(f"{op}: frames {c.a}..{c.b} were edited since (in another tab); "
                               f"{op} that edit first")
        if self.journal is not None:
            self.journal.append({"op": op, "id": c.id, "client": client})
        stack.pop()
        self._apply(c, to)
        target.setdefault(client, []).append(c)
        self.version += 1
        return c

    def depth(self, client: str = "") -> tuple[int, int]:
        """How many edits ``client`` can undo and redo."""
        return len(self.undo_stacks.get(client, ())), len(self.redo_stacks.get(client, ()))

    def attach_journal(self, journal) -> int:
        """Replay ``journal``'s entries (edits as their stored rows, no re-solve), then record into it.
        Returns the number of entries replayed."""
        for e in journal.entries:
            client = str(e.get("client", ""))
            if e.get("op") == "edit":
                after = np.asarray(e["after"], dtype=np.float64)
                a, b = int(e["a"]), int(e["b"])
                if not (0 <= a <= b < self.n_frames and after.shape == (b - a + 1, len(self.names))
                        and np.all(np.isfinite(after))):
                    raise ValueError(f"{journal.path}: edit {e.get('id')} does not fit this take")
                self._record_edit(a, b, after, client)
            else:
                undo = e.get("op") == "undo"
                stack = (self.undo_stacks if undo else self.redo_stacks).get(client)
                if not stack or stack[-1].id != e.get("id"):
                    raise ValueError(f"{journal.path}: {e.get('op')} of edit {e.get('id')} out of order")
                (self.undo if undo else self.redo)(client)
        self.version = max([self.version, *(int(e.get("id", 0)) for e in journal.entries)])
        n, journal.entries = len(journal.entries), []  # now in the undo stacks: not held twice for the session
        self.journal = journal
        return n

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
        current = self.rig_weights(self.weights[i])
        goals = np.array([p.goal for p in pins], dtype=np.float64)
        start = time.perf_counter()
        w = dm.step(goals, current)
        return w[self._rig_order], time.perf_counter() - start

    # ------------------------------------------------------------------ keys
    def keys(self, max_error: float) -> list[Keys]:
        if not max_error > 0:
            raise ValueError(f"max_error must be > 0, not {max_error}")
        if not np.isfinite(max_error):
            raise ValueError(f"max_error must be finite, not {max_error}")
        if self._keys_cache.get("key") != (max_error, self.version):
            self._keys_cache = {"key": (max_error, self.version),
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

    def linear_keys_glb(self, max_error: float) -> bytes:
        """The curves as shared LINEAR keys within ``max_error`` (for players that drop cubic tangents)."""
        from livecap.review.linear import linear_keys
        from transport.gltf import glb_bytes

        frames = linear_keys(self.times, self.weights, max_error)
        return glb_bytes(self.rig, self.names, self.times[frames], self.weights[frames], name="keys (linear)")

    def weights_csv(self) -> str:
        head = "frame,time," + ",".join(self.names)
        f0 = self.take.first_frame
        rows = [f"{f0 + i},{self.times[i]:.6f}," + ",".join(f"{x:.6g}" for x in w) for i, w in enumerate(self.weights)]
        return "\n".join([head, *rows]) + "\n"
