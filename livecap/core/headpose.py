"""Head pose as receivers want it: relative to the actor's calibrated neutral pose, in the rig's axes.

The stabiliser's pose maps the rig frame into the capture volume (``raw = R @ s + t``, see
livecap.calibration.stabilise), so its rotation includes which way the actor faces and which
axis the capture calls up (Z for Vicon/Qualisys). Taken relative to the neutral pose,
``R0^T R`` is the head's own turn about its rest orientation and ``R0^T (t - t0)`` its shift, both
in the rig's axes: +Y up, +Z out of the face, right-handed (the glTF convention; OBJ rigs are
built so), whatever the capture's axes. Unity (VMC) is left-handed with the same up and
forward, so its pose is the mirror image in X.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class NeutralPose:
    """The head's rest pose in the capture volume: rotation (3 x 3) and translation (mm)."""

    rotation: np.ndarray
    translation: np.ndarray

    @classmethod
    def mean_of(cls, quaternions: np.ndarray, translations: np.ndarray) -> NeutralPose:
        """Mean pose over a neutral window (quaternions x, y, z, w; translations mm)."""
        q = np.asarray(quaternions, dtype=np.float64).reshape(-1, 4)
        t = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
        ok = np.isfinite(q).all(axis=1) & np.isfinite(t).all(axis=1) & (np.linalg.norm(q, axis=1) > 0)
        if not ok.any():
            return cls(np.eye(3), np.zeros(3))
        return cls(Rotation.from_quat(q[ok]).mean().as_matrix(), t[ok].mean(axis=0))

    @cached_property
    def _inverse(self) -> Rotation:
        """Built once per pose: from_matrix costs ~0.1 ms, per frame and per sink otherwise."""
        return Rotation.from_matrix(self.rotation.T)

    def relative(self, quaternions: np.ndarray, translations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Head rotation (x, y, z, w) and shift (metres) relative to this pose, in the rig's axes."""
        q = np.asarray(quaternions, dtype=np.float64)
        t = np.asarray(translations, dtype=np.float64)
        if q.shape == (4,):  # a live frame: scipy's per-call overhead (~0.1 ms) is most of a sink's time
            x, y, z, w = q.tolist()
            n = math.sqrt(x * x + y * y + z * z + w * w)
            unit = (x / n, y / n, z / n, w / n)
            if self.identity:  # a source already relative to its neutral (the iPhone's): nothing to undo
                return np.array(unit), t / 1000.0
            shift = (t.reshape(-1, 3) - self.translation) @ self.rotation / 1000.0
            return hamilton(self._inverse_quat, unit), shift.reshape(t.shape)
        shift = (t.reshape(-1, 3) - self.translation) @ self.rotation / 1000.0
        rel = self._inverse * Rotation.from_quat(q.reshape(-1, 4))
        return rel.as_quat().reshape(q.shape), shift.reshape(t.shape)

    @cached_property
    def identity(self) -> bool:
        """The identity pose: a source already relative to its own neutral (the iPhone's)."""
        return bool(np.array_equal(self.rotation, np.eye(3)) and not np.any(self.translation))

    @cached_property
    def _inverse_quat(self) -> np.ndarray:
        return self._inverse.as_quat()


def hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Quaternion product ``a b`` (x, y, z, w): the rotation b, then a."""
    # Python floats: numpy scalar arithmetic costs ~10x more per operation on a per-packet path (docs/iphone.md)
    ax, ay, az, aw = a.tolist() if isinstance(a, np.ndarray) and a.ndim == 1 else a
    bx, by, bz, bw = b.tolist() if isinstance(b, np.ndarray) and b.ndim == 1 else b
    return np.array([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz])


def to_unity(quaternion: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Right-handed Y-up (rig, glTF) -> Unity's left-handed Y-up: mirror X (x -> -x)."""
    q = np.array(quaternion, dtype=np.float64)
    p = np.array(position, dtype=np.float64)
    q[..., 1:3] *= -1.0
    p[..., 0] *= -1.0
    return q, p


class NeutralWindow:
    """The neutral pose of a live stream: the mean over its first ``frames`` frames (the window a
    live session calibrates its neutral face on, livecap run --neutral-seconds), fixed after that;
    until then the mean so far. Sinks ask it for each frame's pose relative to the neutral."""

    def __init__(self, frames: int = 1) -> None:
        self.frames = max(1, int(frames))
        self._q: list[np.ndarray] = []
        self._t: list[np.ndarray] = []
        self.pose: NeutralPose | None = None
        self.identity = False  # fixed to the identity: every rotation is its own relative one

    def fix(self, pose: NeutralPose) -> None:
        """Use ``pose`` from now on: a source whose angles are already relative to its own neutral
        (the iPhone's) passes them through with the identity (:attr:`identity`, which a sink may test
        to skip :meth:`relative` per packet)."""
        self.frames = 0
        self.pose = pose
        self.identity = pose.identity

    def relative(self, quaternion: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(quaternion, dtype=np.float64)
        t = np.asarray(translation, dtype=np.float64)
        qs, ts = q.ravel().tolist(), t.ravel().tolist()  # floats: a per-frame path (docs/iphone.md, Latency)
        if not all(map(math.isfinite, qs + ts)) or math.sqrt(sum(v * v for v in qs)) < 1e-9:
            return np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3)
        if len(self._q) < self.frames:
            self._q.append(q)
            self._t.append(t)
            self.pose = NeutralPose.mean_of(np.array(self._q), np.array(self._t))
        return self.pose.relative(q, t)
