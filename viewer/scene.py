"""Where things are drawn: camera framing, head pose, and the map from the actor's head frame to the rig's.

The head pose follows the project convention ``raw = R @ stabilised + t`` (quaternion x, y, z, w).
Calibration relates the rig to the actor by a similarity ``actor = s R_s rig + t_s`` (Seol et al.
2012 §3.2, proportion matching; Umeyama fit of the neutral marker sites), so a pose measured in
the actor's head frame acts on the rig as ``Sim^-1 . Pose . Sim`` (a rigid motion in rig units).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def quat_matrix(q) -> np.ndarray:
    """3x3 rotation of a unit quaternion (x, y, z, w); normalised first so float noise is harmless."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / max(np.linalg.norm(q), 1e-300)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def affine(linear: np.ndarray, translation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = translation
    return m


def pose_matrix(rotation=None, translation=None) -> np.ndarray:
    """4x4 head-to-world pose; missing parts are identity."""
    R = np.eye(3) if rotation is None else quat_matrix(rotation)
    return affine(R, np.zeros(3) if translation is None else translation)


def transform(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    return p @ m[:3, :3].T + m[:3, 3]


@dataclass(frozen=True)
class Similarity:
    """``head = scale * rotation @ rig + translation``: the rig placed in an actor's head frame."""

    scale: float = 1.0
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def fit(cls, rig_points: np.ndarray, head_points: np.ndarray) -> Similarity:
        """Least-squares similarity (Umeyama) from rig marker sites to the actor's neutral markers."""
        from solvers.rigid import similarity

        s, R, t = similarity(np.asarray(rig_points, float), np.asarray(head_points, float))
        return cls(s, R, t)

    def matrix(self) -> np.ndarray:
        return affine(self.scale * self.rotation, self.translation)

    def inverse(self) -> np.ndarray:
        return affine(self.rotation.T / self.scale, -self.rotation.T @ self.translation / self.scale)

    def displacement_to_rig(self, d: np.ndarray) -> np.ndarray:
        """Actor displacements (..., 3) in rig units and axes: R_s^T d / s."""
        return np.asarray(d, dtype=np.float64) @ self.rotation / self.scale


def model_matrix(rotation, translation, head: Similarity | None = None,
                 display: Similarity | None = None) -> np.ndarray:
    """Rig-to-display transform for one frame: ``display^-1 . Pose . head``.

    ``head`` places the rig in the head frame the pose was measured in; ``display`` chooses the
    shared frame everything is drawn in (default: the same), so a ground-truth panel whose head
    frame differs from the solver's still lines up with it.
    """
    head = head or Similarity()
    display = display or head
    return display.inverse() @ pose_matrix(rotation, translation) @ head.matrix()


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    s = np.cross(f, up)
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def perspective(fov_y_deg: float, aspect: float, near: float, far: float) -> np.ndarray:
    f = 1.0 / np.tan(np.radians(fov_y_deg) / 2)
    m = np.zeros((4, 4))
    m[0, 0], m[1, 1] = f / aspect, f
    m[2, 2] = (far + near) / (near - far)
    m[2, 3] = 2 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


@dataclass
class Camera:
    """A fixed perspective camera framing the rig's neutral face from the front (+z, y up)."""

    eye: np.ndarray
    target: np.ndarray
    fov_y: float = 28.0
    near: float = 10.0
    far: float = 10000.0
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)

    @classmethod
    def frame(cls, points: np.ndarray, aspect: float, margin: float = 1.3, fov_y: float = 28.0,
              yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> Camera:
        """Fit the bounding box of ``points`` (with ``margin`` room for head motion) in view."""
        lo, hi = points.min(0), points.max(0)
        centre = (lo + hi) / 2
        half = (hi - lo) / 2 * margin
        t = np.tan(np.radians(fov_y) / 2)
        dist = max(half[1] / t, half[0] / (t * aspect)) + half[2]
        yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
        direction = np.array([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
        extent = float(np.linalg.norm(hi - lo))
        return cls(centre + dist * direction, centre, fov_y, near=max(dist - 2 * extent, dist * 0.05),
                   far=dist + 2 * extent)

    def view(self) -> np.ndarray:
        return look_at(self.eye, self.target, self.up)

    def projection(self, aspect: float) -> np.ndarray:
        return perspective(self.fov_y, aspect, self.near, self.far)

    def view_projection(self, aspect: float) -> np.ndarray:
        return self.projection(aspect) @ self.view()


def project(view_proj: np.ndarray, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Pixel coordinates (x right, y down, pixel centres at +0.5) of display-space points."""
    w, h = size
    p = np.asarray(points, dtype=np.float64)
    clip = np.c_[p, np.ones(len(p))] @ view_proj.T
    ndc = clip[:, :3] / clip[:, 3:4]
    return np.stack([(ndc[:, 0] + 1) / 2 * w, (1 - ndc[:, 1]) / 2 * h], axis=1)


def vertex_normals(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals of a triangle mesh (the CPU reference for the GPU pass)."""
    p = np.asarray(positions, dtype=np.float64)
    a, b, c = p[triangles[:, 0]], p[triangles[:, 1]], p[triangles[:, 2]]
    fn = np.cross(b - a, c - a)
    n = np.zeros_like(p)
    for k in range(3):
        np.add.at(n, triangles[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.where(length > 0, length, 1), [0.0, 0.0, 1.0])
