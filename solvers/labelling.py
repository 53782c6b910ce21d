"""Labelling unlabelled facial marker clouds against a calibrated shape model.

An optical system hands over each frame's points unordered, with ghosts (reflections) and
gaps; facial markers sit too close together for its own labeller. Every frame, each label's
position is predicted from the head pose and the last fitted blendshape weights through the
marker basis B (the rig is a strong shape model of where the markers can be; Seol et al. 2012
§3). Labels and points are then matched one-to-one by ``scipy.optimize.linear_sum_assignment``
on squared distance clipped at the gate, which is exactly the assignment in which a label may
stay unmatched (missing) at the cost of the gate and a point may stay unused (ghost) — labels
tracked last frame first, then the missing ones on the leftovers; watched close pairs (eyelids)
whose two readings are within noise are withheld. The head pose is re-fitted on the labelled
stable markers (Kabsch; Arun et al. 1987) and the weights on all labelled ones (ridge least
squares, clipped to the rig's limits).

Without a track (first frame, or after too many poorly labelled frames) the neutral
constellation is fitted to the cloud: the principal axes of both give 24 axis-aligned rotation
candidates (also turned by 30 and 60 degrees about an axis whose other two spreads are close, see
``start_rotations``), each refined by a similarity ICP whose steps are the same gated assignment
(Besl & McKay 1992; Umeyama 1991 for the scale): every start for the first few steps, the best
few to the end, and the best is kept.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from solvers.rigid import kabsch


@dataclass(frozen=True)
class LabellerSettings:
    gate_mm: float = 6.0  # a label further than this from its prediction stays missing
    reacquire_growth: float = 0.15  # a missing label's gate grows by this fraction per frame missing
    reacquire_max: float = 2.0  # ... up to this multiple of gate_mm
    ridge: float = 1e-3  # shape fit ridge, relative to the basis' mean squared column norm
    min_labelled: float = 0.5  # a frame labelling fewer than this fraction of labels is poor
    lost_after: int = 3  # consecutive poor frames that end the track (re-initialise)
    limit_slack: float = 0.5  # the fit's weights may pass the rig's limits by this fraction of their range
    reject_mm: float = 6.0  # a labelled point this far from the fitted model is dropped (ghost or swap)
    refine_at: int = 3  # this many labels missing and points unused: re-fit from a wide gate
    confirm_mm: float = 4.0  # a label coming back is kept when two frames in a row give it points this close
    close_pair_mm: float = 15.0  # label pairs this close at rest are watched for meeting (blinks)
    recheck_frames: int = 2  # frames after two labels' predictions met that get a second opinion
    ambiguity_mm2: float = 5.0  # a watched pair whose two pairings' squared distances differ by less is withheld
    init_iterations: int = 20
    init_gate_mm: float = 25.0  # the ICP's first gate; it shrinks to gate_mm
    init_screen: int = 6  # every start runs this many ICP iterations ...
    init_keep: int = 4  # ... and the best this many run the rest
    scale_range: tuple[float, float] = (0.8, 1.25)


@dataclass
class LabelFrame:
    """One frame's labelling: ``index[i]`` is the point given label i, or -1 (missing)."""

    index: np.ndarray  # n int
    positions: np.ndarray  # n x 3 labelled points (0 where missing)
    valid: np.ndarray  # n bool
    initialised: bool  # this frame started a new track
    late: np.ndarray | None = None  # labels confirmed now whose previous frame's point was withheld
    late_index: np.ndarray | None = None  # ... that point's index in the previous frame


@dataclass(frozen=True)
class Fit:
    """A rigid fit of the neutral constellation to a cloud: labels within the gate, gated cost, centre."""

    labelled: int
    cost: float  # sum over labels of min(d^2, gate^2), mm^2
    centre: np.ndarray


def _axis_rotations() -> np.ndarray:
    """The 24 proper rotations that permute and flip coordinate axes."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            M = np.zeros((3, 3))
            M[np.arange(3), perm] = signs
            if np.linalg.det(M) > 0:
                out.append(M)
    return np.array(out)


_AXIS_ROTATIONS = _axis_rotations()
CLOSE_AXES = 1.5  # principal spreads closer than this ratio leave their axes' turn in their plane uncertain
_EMPTY = np.zeros(0, dtype=np.int64)
_ROWS = np.arange(1024)
TREE_POINTS = 256  # a cloud larger than this is searched through a KD-tree while initialising
NEAR_MARGIN_MM = 60.0  # beyond the tracked face's radius plus this, no gate or second opinion reaches


def _rigid(src: np.ndarray, dst: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Kabsch (Arun et al. 1987) for the per-frame head re-fit: ``R scale src + t ~ dst``. The
    rotation is the polar factor of the cross-covariance (one product less the centroids' outer
    product; the scale does not change it), by scaled Newton iteration X <- (g X + X^-T / g) / 2
    (Higham 1986) in plain floats, no LAPACK call; SVD when the covariance is singular or
    reflected. After the first step every singular value is 1 + e >= 1, the Frobenius scaling
    g = (|X^-1| / |X|)^(1/2) ~ 1 - sum(e) / 3 and a step maps e to ~e^2 / 2: the step taken at
    1 - g < 1e-6 leaves ~1e-11 (quadratic convergence)."""
    k = len(src)
    inv = 1.0 / k
    s0, s1, s2 = src.sum(0).tolist()
    d0, d1, d2 = dst.sum(0).tolist()
    (h00, h01, h02), (h10, h11, h12), (h20, h21, h22) = (dst.T @ src).tolist()
    s0, s1, s2, d0, d1, d2 = s0 * inv, s1 * inv, s2 * inv, d0 * inv, d1 * inv, d2 * inv
    m00, m01, m02 = h00 - k * d0 * s0, h01 - k * d0 * s1, h02 - k * d0 * s2
    m10, m11, m12 = h10 - k * d1 * s0, h11 - k * d1 * s1, h12 - k * d1 * s2
    m20, m21, m22 = h20 - k * d2 * s0, h21 - k * d2 * s1, h22 - k * d2 * s2
    c00, c01, c02 = m11 * m22 - m12 * m21, m12 * m20 - m10 * m22, m10 * m21 - m11 * m20
    if m00 * c00 + m01 * c01 + m02 * c02 <= 1e-12 * (abs(m00) + abs(m11) + abs(m22)) ** 3:
        cs, cd = np.array((s0, s1, s2)), np.array((d0, d1, d2))
        return _rigid_svd(src - cs, dst - cd, scale * cs, cd)
    for i in range(12):  # the iterates keep det > 0
        c00, c01, c02 = m11 * m22 - m12 * m21, m12 * m20 - m10 * m22, m10 * m21 - m11 * m20
        c10, c11, c12 = m02 * m21 - m01 * m22, m00 * m22 - m02 * m20, m01 * m20 - m00 * m21
        c20, c21, c22 = m01 * m12 - m02 * m11, m02 * m10 - m00 * m12, m00 * m11 - m01 * m10
        det = m00 * c00 + m01 * c01 + m02 * c02
        nx = m00 * m00 + m01 * m01 + m02 * m02 + m10 * m10 + m11 * m11 + m12 * m12 + m20 * m20 + m21 * m21 + m22 * m22
        nc = c00 * c00 + c01 * c01 + c02 * c02 + c10 * c10 + c11 * c11 + c12 * c12 + c20 * c20 + c21 * c21 + c22 * c22
        g = (nc / (nx * det * det)) ** 0.25
        a, b = 0.5 * g, 0.5 / (g * det)
        m00, m01, m02 = a * m00 + b * c00, a * m01 + b * c01, a * m02 + b * c02
        m10, m11, m12 = a * m10 + b * c10, a * m11 + b * c11, a * m12 + b * c12
        m20, m21, m22 = a * m20 + b * c20, a * m21 + b * c21, a * m22 + b * c22
        if i and 1.0 - g < 1e-6:
            break
    R = np.array(((m00, m01, m02), (m10, m11, m12), (m20, m21, m22)))
    s0, s1, s2 = scale * s0, scale * s1, scale * s2
    t = np.array((d0 - m00 * s0 - m01 * s1 - m02 * s2, d1 - m10 * s0 - m11 * s1 - m12 * s2,
                  d2 - m20 * s0 - m21 * s1 - m22 * s2))
    return R, t


def _rigid_svd(src: np.ndarray, dst: np.ndarray, cs: np.ndarray, cd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    U, _, Vt = np.linalg.svd(src.T @ dst)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        Vt[2] = -Vt[2]
    R = Vt.T @ U.T
    return R, cd - R @ cs


def _principal_axes(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Principal axes (columns, a proper rotation) and standard deviations along them, ascending."""
    c = p - p.mean(0)
    vals, vecs = np.linalg.eigh(c.T @ c)
    if np.linalg.det(vecs) < 0:
        vecs[:, 0] = -vecs[:, 0]
    return vecs, np.sqrt(np.maximum(vals, 0.0) / len(p))


def start_rotations(axes_q: np.ndarray, sd_q: np.ndarray, axes_n: np.ndarray, close: float = CLOSE_AXES,
                    step_deg: float = 30.0) -> list[np.ndarray]:
    """Rotations from the model's principal axes onto the cloud's: the 24 axis permutations and
    flips, and, about each cloud axis whose other two spreads are within ``close`` of each other,
    the same turned by multiples of ``step_deg``. Two near-equal spreads leave their axes free to
    turn in their plane with a few missing markers or ghosts (a face's width and height: 36 and
    44 mm on the demo rig; up to 30 degrees off measured), and the similarity ICP only recovers
    from about 15 degrees."""
    base = [axes_q @ M @ axes_n.T for M in _AXIS_ROTATIONS]
    out = list(base)
    turns = np.radians(np.arange(step_deg, 90.0, step_deg))
    for k in range(3):
        a, b = np.delete(sd_q, k)
        if min(a, b) > 0 and max(a, b) / min(a, b) < close:
            for T in Rotation.from_rotvec(turns[:, None] * axes_q[:, k]).as_matrix():
                out += [T @ R for R in base]
    return out


def _sqdist(pred: np.ndarray, points: np.ndarray) -> np.ndarray:
    """All squared label-point distances by one matmul."""
    return np.einsum("ij,ij->i", pred, pred)[:, None] + np.einsum("ij,ij->i", points, points) - 2.0 * (pred @ points.T)


def _assign(d: np.ndarray, g2: np.ndarray) -> tuple[np.ndarray, float]:
    """Row -> column (-1: none) minimising the sum of min(d, g2) over rows, and the largest squared
    distance assigned (0 when none).

    A row whose nearest column within its gate is nobody else's nearest is at its own minimum;
    only the rows and columns connected to a conflict through within-gate pairs can do better
    by trading, so the Hungarian solve runs on that component alone (exact: every pair outside it
    costs the gate, the same as staying unmatched). A row with gate 0 takes nothing.
    """
    rows = _ROWS[: len(d)] if len(d) <= len(_ROWS) else np.arange(len(d))
    near = d.argmin(1)
    dn = d[rows, near]
    inside = dn < g2
    index = np.where(inside, near, -1)
    if np.maximum.reduce(np.bincount(near, inside)) <= 1:
        return index, float(np.maximum.reduce(dn, initial=0.0, where=inside))
    chosen = near[inside]
    within = d < g2[:, None]
    rows = inside & (np.bincount(chosen, minlength=d.shape[1])[near] > 1)
    while True:
        cols = within[rows].any(0)
        grown = within[:, cols].any(1)
        if (grown == rows).all():
            break
        rows = grown
    r, c = np.flatnonzero(rows), np.flatnonzero(cols)
    sub = np.minimum(d[np.ix_(r, c)], g2[r, None])
    rr, cc = linear_sum_assignment(sub)
    index[r] = -1
    keep = sub[rr, cc] < g2[r[rr]]
    index[r[rr[keep]]] = c[cc[keep]]
    got = np.flatnonzero(index >= 0)
    return index, float(d[got, index[got]].max(initial=0.0))


def gated_assignment(pred: np.ndarray, points: np.ndarray, gate: float | np.ndarray,
                     tree: cKDTree | None = None) -> tuple[np.ndarray, float]:
    """Label -> point index (-1: missing) minimising the sum of min(d^2, gate^2), and that sum.

    ``gate`` may be one per label: the one-to-one assignment in which a label may stay missing at
    the gate's cost and a point unused (a ghost). ``tree`` (a KD-tree of ``points``): only the
    points within some label's gate are looked at (the same assignment: every other point costs
    the gate for every label), so a large cloud costs its neighbourhood, not its size.
    """
    n = len(pred)
    g2 = np.full(n, float(gate) ** 2) if np.isscalar(gate) else np.asarray(gate, dtype=np.float64) ** 2
    if len(points) == 0:
        return np.full(n, -1, dtype=np.int64), float(g2.sum())
    if tree is not None:
        balls = tree.query_ball_point(pred, math.sqrt(float(g2.max())))
        cols = np.unique(np.fromiter(itertools.chain.from_iterable(balls), dtype=np.int64))
        if len(cols) == 0:
            return np.full(n, -1, dtype=np.int64), float(g2.sum())
        index, cost = gated_assignment(pred, points[cols], np.sqrt(g2))
        return np.where(index >= 0, cols[np.maximum(index, 0)], -1), cost
    d = _sqdist(pred, points)
    index, _ = _assign(d, g2)
    cost = np.where(index >= 0, d[np.arange(n), np.maximum(index, 0)], g2)
    return index, float(cost.sum())


def _similarity(src: np.ndarray, dst: np.ndarray, lo: float, hi: float) -> tuple[float, np.ndarray, np.ndarray]:
    """s, R, t with s R src + t ~ dst, s clamped to [lo, hi] (Umeyama 1991)."""
    R, _ = kabsch(src, dst)
    cs, cd = src.mean(0), dst.mean(0)
    den = float(np.sum((src - cs) ** 2))
    s = float(np.sum((dst - cd) * ((src - cs) @ R.T)) / den) if den > 0 else 1.0
    s = min(max(s, lo), hi)
    return s, R, cd - s * R @ cs


class MarkerLabeller:
    """Streaming labeller: ``step(points)`` per frame; expensive preparation once.

    ``neutral`` (n x 3) and ``basis`` (3n x m) are the calibrated actor's rest markers and marker
    basis in the head frame; ``stable`` flags the head-stabilisation markers.
    """

    def __init__(self, neutral: np.ndarray, stable: np.ndarray, basis: np.ndarray, lower: np.ndarray,
                 upper: np.ndarray, settings: LabellerSettings | None = None) -> None:
        self.settings = settings or LabellerSettings()
        self.neutral = np.asarray(neutral, dtype=np.float64)
        self.n = len(self.neutral)
        self.stable = np.asarray(stable, dtype=bool)
        self.basis = np.asarray(basis, dtype=np.float64)
        span = np.asarray(upper, dtype=np.float64) - np.asarray(lower, dtype=np.float64)
        self.lower = np.asarray(lower, dtype=np.float64) - self.settings.limit_slack * span
        self.upper = np.asarray(upper, dtype=np.float64) + self.settings.limit_slack * span
        m = self.basis.shape[1]
        gram = self.basis.T @ self.basis
        lam = self.settings.ridge * float(np.trace(gram)) / max(m, 1)
        self._gram = gram + lam * np.eye(m)
        self._fit = np.linalg.solve(self._gram, self.basis.T)  # m x 3n
        self._fit_offset = self._fit @ self.neutral.ravel()
        rows = self.basis.reshape(self.n, 3, m)
        self._marker_gram = np.einsum("nki,nkj->nij", rows, rows)  # each marker's share of the gram
        gap = np.linalg.norm(self.neutral[:, None] - self.neutral[None], axis=-1)
        self._pairs = np.argwhere(np.triu(gap < self.settings.close_pair_mm, 1)).T  # 2 x p
        a, b = self._pairs
        self._pair_rest = self.neutral[a] - self.neutral[b]
        self._pair_basis = (rows[a] - rows[b]).reshape(-1, m)  # the pairs' separations through the basis
        self._stable_idx = np.flatnonzero(self.stable)
        centred = self.neutral - self.neutral.mean(0)
        self._reach = (self.settings.scale_range[1] * math.sqrt(float(np.maximum.reduce(np.vecdot(centred, centred))))
                       + self.settings.gate_mm)  # a face's radius, at the largest scale, plus a gate
        self._zero_w = np.clip(np.zeros(m), lower, upper)
        self._g2 = np.full(self.n, self.settings.gate_mm ** 2)
        # one product gives the model and the watched pairs' separations
        self._shape_basis = np.vstack([self.basis, self._pair_basis])
        self._shape_rest = np.concatenate([self.neutral.ravel(), self._pair_rest.ravel()])
        self._pred = np.ones((self.n, 5))  # world prediction rows [x, |x|^2, 1] ...
        self._cloud = np.ones((64, 5))  # ... and cloud rows [-2p, 1, |p|^2]: their product is |x - p|^2
        self.reset()

    def reset(self) -> None:
        """Forget the track: the next frame re-initialises from the neutral."""
        self.tracking = False
        self.scale = 1.0
        self.R = np.eye(3)
        self.t = np.zeros(3)
        self.w = self._zero_w.copy()
        self._set_shape(self.w)
        self._predict()
        self.poor = 0
        self.initialisations = 0
        self.refines = 0
        self.rejected = 0
        self.second_opinions = 0
        self.withheld = 0
        self.recheck = 0
        self.missing_for = np.zeros(self.n)
        self._missing = np.zeros(self.n, dtype=bool)
        self._fresh = _EMPTY
        self._no_held = np.zeros(self.n, dtype=bool)
        self._held = self._no_held
        self._candidates = False
        self._sep_min = 0.0
        self._candidate = np.zeros((self.n, 3))
        self._candidate_ok = np.zeros(self.n, dtype=bool)
        self._candidate_index = np.full(self.n, -1, dtype=np.int64)
        self._late = self._late_index = _EMPTY
        self._returning = self._returning_index = _EMPTY
        self.tentative = 0
        self.rival: tuple[Fit, Fit] | None = None  # set by an initialisation that saw a second face

    # ------------------------------------------------------------------ model
    def model(self, w: np.ndarray) -> np.ndarray:
        """Head-frame marker positions for weights ``w`` (n x 3)."""
        return self.neutral + (self.basis @ w).reshape(self.n, 3)

    def _set_shape(self, w: np.ndarray) -> float:
        """The model at weights ``w`` and the watched pairs' separations by one product; returns
        the smallest pair's squared separation (its world distance is kept for the next frame's
        ambiguity test)."""
        full = self._shape_basis @ w
        full += self._shape_rest
        self._model = full[: 3 * self.n].reshape(self.n, 3)
        if len(self._pair_rest) == 0:
            self._sep_min = math.inf
            return math.inf
        sep = full[3 * self.n:].reshape(-1, 3)
        gap2 = float(np.minimum.reduce(np.vecdot(sep, sep)))
        self._sep_min = self.scale * math.sqrt(gap2)
        return gap2

    def _predict(self) -> None:
        """Next frame's world prediction from the current model and pose, as ``_pred`` rows."""
        world = self._world(self._model)
        self._pred[:, :3] = world
        np.vecdot(world, world, out=self._pred[:, 3])

    def _distances(self, points: np.ndarray) -> np.ndarray:
        """Squared distances from every predicted label to every point: one product."""
        k = len(points)
        if k > len(self._cloud):
            self._cloud = np.ones((2 * k, 5))
        q = self._cloud[:k]
        np.multiply(points, -2.0, out=q[:, :3])
        np.vecdot(points, points, out=q[:, 4])
        return self._pred @ q.T

    def _world(self, local: np.ndarray) -> np.ndarray:
        return (self.scale * local) @ self.R.T + self.t

    def _local(self, points: np.ndarray) -> np.ndarray:
        return ((points - self.t) @ self.R) * (1.0 / self.scale)

    def near(self, points: np.ndarray, margin: float = NEAR_MARGIN_MM) -> np.ndarray | None:
        """Which points the next ``step`` can give a label while tracking (None: every point, no
        track): within the predicted face's radius plus ``margin`` of its centre. Cropping a large
        cloud (a body capture around the face) to these leaves the labelling as it is, since no gate
        in use (at most 2 x ``gate_mm``) reaches further, and makes each frame cost the face."""
        if not self.tracking:
            return None
        world = self._pred[:, :3]
        centre = world.mean(0)
        radius = math.sqrt(float(np.maximum.reduce(np.vecdot(world - centre, world - centre)))) + margin
        d = points - centre
        return np.vecdot(d, d) <= radius * radius

    def _fit_shape(self, local: np.ndarray, lab: np.ndarray, complete: bool) -> np.ndarray:
        """Weights from the labelled markers' head-frame positions (missing ones held at their
        prediction: written into the model, which is recomputed from the fit): ridge least squares
        through the precomputed pseudo-inverse. Sets ``w``; returns the n x 3 positions fitted."""
        if not complete:
            self._model[lab] = local
            local = self._model
        w = self._fit @ local.ravel()
        w -= self._fit_offset
        np.maximum(w, self.lower, out=w)
        np.minimum(w, self.upper, out=w)
        self.w = w
        return local

    def _fit_shape_subset(self, points: np.ndarray, index: np.ndarray) -> np.ndarray:
        """Weights from the labelled markers alone (no pull towards the prediction of missing ones)."""
        lab = index >= 0
        gram = self._gram - self._marker_gram[~lab].sum(0)
        local = self._local(points[index[lab]])
        rhs = self.basis.reshape(self.n, 3, -1)[lab].reshape(-1, self.basis.shape[1]).T @ (
            local - self.neutral[lab]).ravel()
        w = np.linalg.solve(gram, rhs)
        np.clip(w, self.lower, self.upper, out=w)
        return w

    def _refine(self, points: np.ndarray, iterations: int, gate: float, tree: cKDTree | None = None) -> np.ndarray:
        """Alternate assignment (wide gate), head pose and shape from the current state: recovers a
        group of labels whose prediction fell behind (a fast jaw) or a fresh start's expression."""
        index = np.full(self.n, -1, dtype=np.int64)
        for _ in range(iterations):
            local = self.model(self.w)
            index, _ = gated_assignment(self._world(local), points, gate, tree)
            if not self._fit_pose(points, index, local):
                break
            self.w = self._fit_shape_subset(points, index)
        return index

    def _fit_pose(self, points: np.ndarray, index: np.ndarray, local: np.ndarray) -> bool:
        ist = index[self._stable_idx]
        if np.minimum.reduce(ist) >= 0:
            self.R, self.t = _rigid(local[self._stable_idx], points[ist], self.scale)
            return True
        use = self._stable_idx[ist >= 0]
        if len(use) < 3:
            use = np.flatnonzero(index >= 0)
            if len(use) < 3:
                return False
        self.R, self.t = _rigid(local[use], points[index[use]], self.scale)
        return True

    # ------------------------------------------------------------------ streaming
    def step(self, points: np.ndarray) -> LabelFrame:
        """Label one frame's unordered points (k x 3, any k)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not math.isfinite(points.sum()):
            points = points[np.isfinite(points).all(1)]
        if not self.tracking:
            index = self.initialise(points)
            return self._frame(points, index, index >= 0, True)
        s = self.settings
        n = self.n
        index = self._label(points)
        lab = index >= 0
        n_lab = int(np.count_nonzero(lab))
        if n - n_lab >= s.refine_at and len(points) - n_lab >= s.refine_at:
            self.refines += 1
            self._refine(points, 3, 2 * s.gate_mm)
            self._set_shape(self.w)
            self._sep_min = 0.0
            self._predict()
            index = self._label(points)
            lab = index >= 0
            n_lab = int(np.count_nonzero(lab))
        self._late = self._late_index = self._returning = self._returning_index = _EMPTY
        if len(self._fresh):
            self._confirm(points, index, self._fresh)
            lab = index >= 0
            n_lab = int(np.count_nonzero(lab))
        elif self._candidates:
            self._candidate_ok[:] = False
            self._candidates = False
        self.missing_for += 1.0
        self.missing_for[lab if self._held is self._no_held else lab | self._held] = 0.0
        if self._fit_pose(points, index, self._model):
            complete = n_lab == n
            fitted = self._fit_shape(self._local(points[index] if complete else points[index[lab]]), lab, complete)
            gap2 = self._set_shape(self.w)
            res = fitted - self._model
            r2 = np.vecdot(res, res)
            if np.maximum.reduce(r2, initial=0.0, where=lab) > s.reject_mm ** 2:
                far = (r2 > s.reject_mm ** 2) & lab
                self.rejected += int(far.sum())
                index[far] = -1
                if self._second_opinion(points):
                    index = self._settle(points)
                lab = index >= 0
                n_lab = int(np.count_nonzero(lab))
            elif self._pairs_met(gap2) and self._second_opinion(points):
                index = self._settle(points)
                lab = index >= 0
                n_lab = int(np.count_nonzero(lab))
        if n_lab < s.min_labelled * n:
            self.poor += 1
            if self.poor >= s.lost_after:
                self.tracking = False
        else:
            self.poor = 0
        self._predict()
        return self._frame(points, index, lab, False)

    def _label(self, points: np.ndarray) -> np.ndarray:
        """Labels tracked last frame are assigned first (a track keeps its point rather than
        hand it to a label that was missing: an occluded lid must not take the other lid's point
        at a blink); watched pairs whose assignment is within noise are withheld; labels that were
        missing take leftover points within a gate growing with the time missing (``_fresh``)."""
        self._held = self._no_held
        self._fresh = _EMPTY
        missing = self._missing = self.missing_for > 0
        if len(points) == 0:
            return np.full(self.n, -1, dtype=np.int64)
        d = self._distances(points)
        lost = missing.nonzero()[0]
        if len(lost) == 0:
            index, e2 = _assign(d, self._g2)
            self._withhold(d, index, e2, self._sep_min)
            return index
        index, e2 = _assign(d, np.where(missing, 0.0, self._g2))
        self._withhold(d, index, e2, self._sep_min)
        self._reacquire(d, index, lost)
        return index

    def _withhold(self, d: np.ndarray, index: np.ndarray, e2: float, sep: float) -> None:
        """Watched pairs (eyelids at a blink) whose two possible pairings cost within
        ``ambiguity_mm2`` of each other — or whose one point is about as near to either — are
        left unlabelled this frame: within marker noise either reading is as likely, and a wrong
        one would carry into the next prediction. They stay tracked.

        Skipped when no pair can be: with every assigned point within e (``e2`` = e^2) of its
        prediction and every pair's predictions at least ``sep`` apart (0: unknown), either pairing
        of a pair differs by at least sep (sep - 2e)."""
        if sep > 0.0:
            e = math.sqrt(e2)
            if sep * (sep - 2.0 * e) >= self.settings.ambiguity_mm2 and sep > 2.0 * e:
                return
        d = np.concatenate([d, np.zeros((self.n, 1))], axis=1)  # index -1 (missing) reads no distance
        a, b = self._pairs
        ia, ib = index[a], index[b]
        delta = d[b, ia] - d[a, ia] + d[a, ib] - d[b, ib]
        amb = (delta < self.settings.ambiguity_mm2) & (ia + ib > -2)
        if amb.any():
            self._held = np.zeros(self.n, dtype=bool)
            self._held[a[amb]] = True
            self._held[b[amb]] = True
            self.withheld += int(np.count_nonzero(index[self._held] >= 0))
            index[self._held] = -1

    def _confirm(self, points: np.ndarray, index: np.ndarray, fresh: np.ndarray) -> None:
        """A label that was missing takes a point only when the frame before offered it one within
        ``confirm_mm``: a ghost near an occluded marker's prediction rarely comes twice, a marker
        coming back does (live, one frame of it is lost; offline it is put back, see ``late``)."""
        p = points[index[fresh]]
        d = p - self._candidate[fresh]
        ok = self._candidate_ok[fresh] & (np.vecdot(d, d) < self.settings.confirm_mm ** 2)
        kept = fresh[ok]
        self._late, self._late_index = kept, self._candidate_index[kept]
        self._candidate_ok[:] = False
        self._candidate[fresh] = p
        self._candidate_index[fresh] = index[fresh]
        self._candidate_ok[fresh] = True
        self._candidates = True
        if len(kept) < len(fresh):
            index[fresh[~ok]] = -1
            self.tentative += len(fresh) - len(kept)
        self._returning, self._returning_index = kept, index[kept]

    def _pairs_met(self, gap2: float) -> bool:
        """True on the frames just after two watched labels' model positions came within the gate
        (``gap2``: the closest pair's squared separation)."""
        if gap2 < self.settings.gate_mm ** 2:
            self.recheck = self.settings.recheck_frames
            return True
        if self.recheck > 0:
            self.recheck -= 1
            return True
        return False

    def _second_opinion(self, points: np.ndarray) -> bool:
        """After a rejection or a blink: the track may carry a consistent swap (two lid markers
        that met). Re-fit the shape from the neutral at the current head pose and keep whichever
        of the two explains the cloud better (gated cost)."""
        g = self.settings.gate_mm
        _, kept = gated_assignment(self._world(self.model(self.w)), points, g)
        state = (self.w.copy(), self.R.copy(), self.t.copy())
        self.w = self._zero_w.copy()
        self._refine(points, 3, g)
        _, fresh = gated_assignment(self._world(self.model(self.w)), points, g)
        if fresh < kept:
            self.second_opinions += 1
            return True
        self.w, self.R, self.t = state
        return False

    def _settle(self, points: np.ndarray) -> np.ndarray:
        """Labels from the second opinion's pose and shape: the labels tracked before this frame
        are re-assigned; those that came back this frame (confirmed) keep their point if free."""
        self._set_shape(self.w)
        d = _sqdist(self._world(self._model), points)
        index = np.full(self.n, -1, dtype=np.int64)
        rows = np.flatnonzero(~self._missing)
        index[rows], _ = _assign(d[rows], self._g2[rows])
        self._held = self._no_held
        self._withhold(d, index, 0.0, 0.0)
        free = ~np.isin(self._returning_index, index[index >= 0])
        index[self._returning[free]] = self._returning_index[free]
        self.missing_for[:] = np.where((index >= 0) | self._held, 0.0, np.maximum(self.missing_for, 1.0))
        return index

    def _reacquire(self, d: np.ndarray, index: np.ndarray, lost: np.ndarray) -> None:
        """Labels missing since last frame (``lost``, none assigned yet; their prediction may have
        drifted) may take points nobody took, within a gate that grows with the time missing; those
        that do are ``_fresh``."""
        s = self.settings
        sub = d[lost]
        sub[:, index[index >= 0]] = np.inf
        if np.minimum.reduce(sub, axis=None) >= (s.gate_mm * s.reacquire_max) ** 2:
            return
        near = sub.min(1)
        gate2 = (s.gate_mm * np.minimum(1.0 + s.reacquire_growth * self.missing_for[lost], s.reacquire_max)) ** 2
        if (near >= gate2).all():
            return
        got, _ = _assign(sub, gate2)
        ok = got >= 0
        self._fresh = lost[ok]
        index[self._fresh] = got[ok]

    def _frame(self, points: np.ndarray, index: np.ndarray, valid: np.ndarray, initialised: bool) -> LabelFrame:
        pos = np.where(valid[:, None], points[index], 0.0) if len(points) else np.zeros((self.n, 3))
        late, self._late = self._late, _EMPTY
        return LabelFrame(index, pos, valid, initialised, late, self._late_index)

    # ------------------------------------------------------------------ (re)initialisation
    def initialise(self, points: np.ndarray) -> np.ndarray:
        """Fit the neutral constellation to the cloud (similarity + assignment search), then the
        shape; starts a track when enough labels are found. Returns the labelling."""
        s = self.settings
        index = np.full(self.n, -1, dtype=np.int64)
        if len(points) < max(3, int(s.min_labelled * self.n)):
            return index
        keep = self._densest(points) if len(points) > 1.5 * self.n else None
        cloud = points if keep is None else points[keep]
        tree = cKDTree(cloud) if len(cloud) > TREE_POINTS else None
        _, (self.scale, self.R, self.t) = self._rigid_search(cloud, tree, self.initialisations > 0)
        # expression: alternate assignment, pose and shape from the best rigid start
        self.w = self._zero_w.copy()
        self._refine(cloud, 5, 2 * s.gate_mm, tree)
        self._set_shape(self.w)
        index, _ = gated_assignment(self._world(self._model), cloud, s.gate_mm, tree)
        if keep is not None:
            index = np.where(index >= 0, keep[np.maximum(index, 0)], -1)
        lab = index >= 0
        self.tracking = lab.sum() >= s.min_labelled * self.n
        self.initialisations += int(self.tracking)
        self.rival = self._rival(points, index, tree if keep is None else None) if self.tracking else None
        self._predict()
        self.poor = 0
        self.missing_for[:] = np.where(lab, 0.0, 1.0)
        self._held = self._no_held
        self._sep_min = 0.0
        return index

    def _rigid_search(self, points: np.ndarray, tree: cKDTree | None, from_last: bool) -> tuple[float, tuple]:
        """The neutral's best similarity pose on the cloud: gated cost, (scale, R, t)."""
        s = self.settings
        lo, hi = s.scale_range
        axes_n, sd_n = _principal_axes(self.neutral)
        axes_q, sd_q = _principal_axes(points)
        spread = math.sqrt((sd_q @ sd_q) / (sd_n @ sd_n))  # ratio of RMS radii about the centroids
        scale0 = min(max(spread, lo), hi)
        starts = [(scale0, R) for R in start_rotations(axes_q, sd_q, axes_n)]
        if from_last:  # a lost track: its last pose is a candidate too
            starts.append((self.scale, self.R))
        gates = np.geomspace(s.init_gate_mm, s.gate_mm, s.init_iterations)
        head, tail = gates[:s.init_screen], gates[s.init_screen:]
        centre, mean_n = points.mean(0), self.neutral.mean(0)
        screened = sorted((self._icp(points, self.neutral, sc, R, centre - sc * R @ mean_n, head, tree)
                           for sc, R in starts), key=lambda fit: fit[0])[:s.init_keep]
        return min((self._icp(points, self.neutral, *state, tail, tree) for _, state in screened),
                   key=lambda fit: fit[0])

    def _fit_score(self, points: np.ndarray, state: tuple, tree: cKDTree | None) -> Fit:
        scale, R, t = state
        index, cost = gated_assignment(scale * self.neutral @ R.T + t, points, self.settings.gate_mm, tree)
        return Fit(int(np.count_nonzero(index >= 0)), cost, scale * self.neutral.mean(0) @ R.T + t)

    def _densest(self, points: np.ndarray) -> np.ndarray:
        """The points about the one with the most others within a face's reach: where a face is in a
        cloud of many more points than one face has (a body capture, a second actor). The search
        starts from that neighbourhood's own centroid and axes, not the whole cloud's."""
        counts = cKDTree(points).query_ball_point(points, self._reach, return_length=True)
        d = points - points[counts.argmax()]
        return np.flatnonzero(np.vecdot(d, d) <= self._reach ** 2)

    def _rival(self, points: np.ndarray, index: np.ndarray, tree: cKDTree | None) -> tuple[Fit, Fit] | None:
        """A second face among the points the new track left unused: (this track's rigid fit, the
        other's), or None. Looked for only where enough unused points lie within a face's reach of
        one another (a KD-tree count), and fitted there alone, so scattered ghosts cost little."""
        s = self.settings
        need = s.min_labelled * self.n
        rest = np.setdiff1d(np.arange(len(points)), index[index >= 0])
        if len(rest) < need:
            return None
        others = points[rest]
        reach = self._reach
        counts = cKDTree(others).query_ball_point(others, reach, return_length=True)
        if counts.max() < need:
            return None
        d = others - others[counts.argmax()]
        near = others[np.vecdot(d, d) <= reach * reach]
        _, state = self._rigid_search(near, None, False)
        second = self._fit_score(near, state, None)
        if second.labelled < need:
            return None
        return self._fit_score(points, (self.scale, self.R, self.t), tree), second

    def _icp(self, points, local, scale, R, t, gates, tree=None):
        """Similarity ICP through the shrinking ``gates``; its cost at the last gate."""
        lo, hi = self.settings.scale_range
        for gate in gates:
            index, _ = gated_assignment(scale * local @ R.T + t, points, gate, tree)
            lab = index >= 0
            if lab.sum() < 3:
                return np.inf, (scale, R, t)
            scale, R, t = _similarity(local[lab], points[index[lab]], lo, hi)
        _, cost = gated_assignment(scale * local @ R.T + t, points, gates[-1], tree)
        return cost, (scale, R, t)
