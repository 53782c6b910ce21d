"""Head-motion removal (Seol et al. 2012 §3.1; Curio et al. 2006 §2.3).

Per frame, the rigid transform that best maps the stable markers' neutral positions onto the
observed ones (Procrustes / Arun et al. 1987 SVD, with the reflection guard). The removed motion
is the head pose, published with the weights. Convention: ``raw = R @ stabilised + t``
(head-to-world), quaternions as (x, y, z, w).

Robustness (beyond the papers, which align to hand-cleaned data): a stable marker that drops out
is simply left out; one that jumps (mislabel, reflection, skin slide) is found by iteratively
reweighted least squares with Tukey's biweight on the stable-marker residuals, started from the
best leave-one-out fit so one gross outlier cannot drag the start. When fewer than three stable
markers are visible the fit falls back to every visible facial marker (with the same robust
weights, which discount the ones the expression moves); with fewer than three visible markers
in all, the last good pose is held.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from scipy.spatial.transform import Rotation

from solvers.rigid import DEGENERATE, HORN_MAP, ROTATION_MAP, kabsch, rotation_from_covariance

TUKEY_C = 4.685  # 95 % efficiency at the Gaussian
MAD_TO_SIGMA = 1.4826
CHECK_SCALES = 3.0  # a residual beyond 3 floors sends the frame through the robust refit
LEAVE_ONE_OUT_MAX = 12  # leave-one-out starts only for small marker sets (stable markers)
_DROP = {k: ~np.eye(k, dtype=bool) for k in range(5, LEAVE_ONE_OUT_MAX + 1)}  # row j leaves marker j out


def to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (x, y, z, w) of rotation matrices (..., 3, 3).

    The same branch-on-the-largest-component method (Shepperd 1978) and sign as
    ``scipy.spatial.transform.Rotation.from_matrix(R).as_quat()``, in plain numpy: the live
    pipeline calls this every frame, and scipy's version costs ~0.25 ms per single matrix.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.ndim > 3:
        return to_quaternion(R.reshape(-1, 3, 3)).reshape(*R.shape[:-2], 4)
    if R.ndim == 2:  # one matrix (every live frame): plain floats, no masks
        m = R.tolist()
        tr = m[0][0] + m[1][1] + m[2][2]
        diag = [m[0][0], m[1][1], m[2][2], tr]
        i = diag.index(max(diag))
        q = [0.0, 0.0, 0.0, 0.0]
        if i == 3:
            q = [m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1], 1 + tr]
        else:
            j, k = (i + 1) % 3, (i + 2) % 3
            q[i] = 1 - tr + 2 * m[i][i]
            q[j] = m[j][i] + m[i][j]
            q[k] = m[k][i] + m[i][k]
            q[3] = m[k][j] - m[j][k]
        out = np.array(q)
        return out / np.sqrt(out @ out)
    d0, d1, d2 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    tr = d0 + d1 + d2
    choice = np.argmax(np.stack([d0, d1, d2, tr], 1), 1)
    q = np.empty((len(R), 4))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        sel = choice == i
        q[sel, i] = 1 - tr[sel] + 2 * R[sel, i, i]
        q[sel, j] = R[sel, j, i] + R[sel, i, j]
        q[sel, k] = R[sel, k, i] + R[sel, i, k]
        q[sel, 3] = R[sel, k, j] - R[sel, j, k]
    sel = choice == 3
    q[sel, 0] = R[sel, 2, 1] - R[sel, 1, 2]
    q[sel, 1] = R[sel, 0, 2] - R[sel, 2, 0]
    q[sel, 2] = R[sel, 1, 0] - R[sel, 0, 1]
    q[sel, 3] = 1 + tr[sel]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _residuals(ref: np.ndarray, pts: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    if R.ndim == 2 and ref.ndim == 2:
        d = ref @ R.T + t - pts
        return np.sqrt(np.einsum("...i,...i->...", d, d))
    fit = ref @ np.swapaxes(R, -1, -2) + t[..., None, :]
    return np.linalg.norm(fit - pts, axis=-1)


def _masked_median(r: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Median of ``r`` over the markers in ``use`` along the last axis (0 where none)."""
    big = np.where(use, r, np.inf)
    srt = np.sort(big, axis=-1)
    cnt = use.sum(-1)
    lo = np.take_along_axis(srt, np.maximum((cnt - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(srt, np.maximum(cnt // 2, 0)[..., None], -1)[..., 0]
    med = 0.5 * (lo + hi)
    return np.where(cnt > 0, med, 0.0)


def _initial(ref: np.ndarray, pts: np.ndarray, use: np.ndarray,
             fits: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares fit, or the leave-one-out fit with the smallest median residual.

    For small sets (stable markers) one gross outlier would bias the plain fit; leaving each marker
    out in turn (k + 1 tiny fits per frame) finds a start that ignores it. ``fits``: those fits' R
    (..., J, 3, 3) and t (..., J, 3), the plain one first, when ``_fit_with_deleted`` has made them.
    """
    k = use.shape[-1]
    drop = ~np.eye(k, dtype=bool)  # row j leaves marker j out
    cand = use[..., None, :] & drop  # (..., k, k)
    if fits is not None:
        Rall, tall = fits
        if Rall.shape[-3] == 1:
            return Rall[..., 0, :, :], tall[..., 0, :]
    else:
        R, t = kabsch(ref, pts, use)
        if k < 5 or k > LEAVE_ONE_OUT_MAX or not (use.sum(-1) >= 5).any():
            return R, t
        Rc, tc = kabsch(ref[..., None, :, :], pts[..., None, :, :], cand)
        Rall = np.concatenate([R[..., None, :, :], Rc], axis=-3)  # (..., k+1, 3, 3)
        tall = np.concatenate([t[..., None, :], tc], axis=-2)
    # leave one out only with 4 or more left: a 3-marker fit has no redundancy to judge by
    ok = np.concatenate([np.ones(use.shape[:-1] + (1,), bool), cand.sum(-1) >= 4], axis=-1)
    ok[..., 1:] &= use  # leaving out a marker that is missing changes nothing
    res = _residuals(ref[..., None, :, :], pts[..., None, :, :], Rall, tall)
    score = np.where(ok, _masked_median(res, use[..., None, :]), np.inf)
    score[..., 0] *= 0.5  # keep the plain fit unless leaving one out halves the median residual
    best = np.argmin(score, axis=-1)
    Rb = np.take_along_axis(Rall, best[..., None, None, None], -3)[..., 0, :, :]
    tb = np.take_along_axis(tall, best[..., None, None], -2)[..., 0, :]
    return Rb, tb


COMPILED_MIN_FRAMES = 8  # from this many frames the check runs compiled (solvers.rigid_take_kernels)


def _fit_with_deleted(ref: np.ndarray, pts: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, ...]:
    """``_fit_with_deleted_batch``'s results; a take (``COMPILED_MIN_FRAMES`` frames or more) in one compiled pass,
    its frames with a fit whose top eigenvalue is not simple redone by the numpy form."""
    k = len(ref)
    lead = pts.shape[:-2]
    P = np.ascontiguousarray(pts, dtype=np.float64).reshape(-1, k, 3)
    if len(P) < COMPILED_MIN_FRAMES:
        return _fit_with_deleted_batch(ref, pts, use)
    from solvers.rigid_take_kernels import fit_with_deleted_take

    U = np.ascontiguousarray(use, dtype=bool).reshape(-1, k)
    J = k + 1 if 5 <= k <= LEAVE_ONE_OUT_MAX else 1
    R, t, r = np.empty((len(P), J, 3, 3)), np.empty((len(P), J, 3)), np.empty((len(P), k))
    redo = fit_with_deleted_take(np.ascontiguousarray(ref, dtype=np.float64), P, U, J > 1, DEGENERATE, R, t, r)
    if redo.any():
        f = np.flatnonzero(redo)
        _, _, r[f], R[f], t[f] = _fit_with_deleted_batch(ref, P[f], U[f])
    return (R[:, 0].reshape(*lead, 3, 3), t[:, 0].reshape(*lead, 3), r.reshape(*lead, k), R.reshape(*lead, J, 3, 3),
            t.reshape(*lead, J, 3))


def _fit_with_deleted_batch(ref: np.ndarray, pts: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, ...]:
    """Rigid fits and each marker's larger of its residual and deleted residual, batched over frames.

    A far (high-leverage) marker that jumps drags the plain fit towards itself and hides in its
    own residual; fitted without it (with 4 or more markers left, sets of 5-12 markers only), the
    jump shows in full. Per frame the fit and the k leave-one-out fits share one set of centred
    products (each leave-one-out covariance is the full one less marker j's term and a centroid
    correction), and all rotations come from one call (Horn 1987, ``solvers.rigid.rotation_from_covariance``).
    ``ref`` (k, 3), ``pts`` (..., k, 3), ``use`` (..., k); returns R (..., 3, 3), t (..., 3), r (..., k) and
    every fit's R (..., J, 3, 3) and t (..., J, 3) (J = k + 1 with leave-one-out, else 1), IRLS's candidate starts.
    """
    k = len(ref)
    lead = pts.shape[:-2]
    P = pts.reshape(-1, k, 3)
    U = use.reshape(-1, k)
    T = len(P)
    loo = 5 <= k <= LEAVE_ONE_OUT_MAX
    W = np.empty((T, k + 1 if loo else 1, k))
    W[:, 0] = U
    if loo:
        np.logical_and(U[:, None, :], _DROP[k], out=W[:, 1:], casting="unsafe")
    wsum = W.sum(-1)  # (T, J): fit 0 uses every marker, fit j + 1 all but marker j
    n = np.maximum(wsum[:, :1], 1e-300)
    ca = (W[:, 0] @ ref) / n
    cb = (W[:, :1] @ P)[:, 0] / n
    a = ref - ca[:, None, :]  # centred once, so the products below lose no digits
    b = P - cb[:, None, :]
    # every fit's sums (of a, b, a b^T, |a|^2 + |b|^2) from one product with the marker weights
    F = np.concatenate([a, b, (a[..., :, None] * b[..., None, :]).reshape(T, k, 9),
                        (a * a).sum(-1, keepdims=True) + (b * b).sum(-1, keepdims=True)], axis=-1)
    G = W @ F
    inv = 1.0 / np.maximum(wsum, 1e-300)[..., None]
    cs = G[..., 0:3] * inv
    cd = G[..., 3:6] * inv
    H = G[..., 6:15] - wsum[..., None] * (cs[..., :, None] * cd[..., None, :]).reshape(T, -1, 9)
    bound = 0.5 * (G[..., 15] - wsum * ((cs * cs).sum(-1) + (cd * cd).sum(-1)))
    R = rotation_from_covariance(H.reshape(T, -1, 3, 3), bound)
    R0 = R[:, 0]
    fit = (a - cs[:, :1]) @ np.swapaxes(R0, -1, -2) + cd[:, :1] - b
    r = np.sqrt((fit * fit).sum(-1))
    if loo:
        own = (R[:, 1:] @ (a - cs[:, 1:])[..., None])[..., 0] + cd[:, 1:] - b
        r = np.where(U & (wsum[:, 1:] >= 4), np.maximum(r, np.sqrt((own * own).sum(-1))), r)
    tall = cb[:, None, :] + cd - (R @ (ca[:, None, :] + cs)[..., None])[..., 0]
    J = R.shape[1]
    return (R0.reshape(*lead, 3, 3), tall[:, 0].reshape(*lead, 3), r.reshape(*lead, k), R.reshape(*lead, J, 3, 3),
            tall.reshape(*lead, J, 3))


def robust_pose(ref: np.ndarray, pts: np.ndarray, use: np.ndarray, iterations: int = 3,
                floor_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rigid fit ``R ref + t ~ pts``, robust to outlying markers; batched over ``pts``' leading axes.

    ``ref`` (k, 3) is shared; ``pts`` (..., k, 3); ``use`` (..., k) marks the markers that may
    take part (at least 3 per frame). ``floor_mm`` is about twice the marker noise. The plain
    least-squares fit stands when every residual is within 3 * ``floor_mm`` (an outlier
    inflates the median, so this check uses the floor alone). Other frames are refitted by
    iteratively reweighted least squares with Tukey's biweight (cut-off 4.685 scales, the scale
    1.4826 * the median residual distance, never below ``floor_mm``), started from the best
    leave-one-out fit. Returns R, t and the per-marker weights used.
    """
    use = np.asarray(use, dtype=bool)
    w = use.astype(np.float64)
    if iterations <= 0:
        R, t = kabsch(ref, pts, use)
        return R, t, w
    R, t, r, Rall, tall = _fit_with_deleted(ref, pts, use)
    bad = (use & (r > CHECK_SCALES * floor_mm)).any(-1)
    if pts.ndim == 2:
        return _irls(ref, pts, use, iterations, floor_mm, (Rall, tall)) if bad else (R, t, w)
    if bad.any():
        f = np.flatnonzero(bad.reshape(-1))
        lead = pts.shape[:-2]
        J = Rall.shape[-3]
        Rf, tf, wf = _irls(ref, pts.reshape(-1, *pts.shape[-2:])[f], use.reshape(-1, use.shape[-1])[f],
                           iterations, floor_mm, (Rall.reshape(-1, J, 3, 3)[f], tall.reshape(-1, J, 3)[f]))
        R, t, w = R.reshape(-1, 3, 3), t.reshape(-1, 3), w.reshape(-1, w.shape[-1])
        R[f], t[f], w[f] = Rf, tf, wf
        R, t, w = R.reshape(*lead, 3, 3), t.reshape(*lead, 3), w.reshape(*lead, -1)
    return R, t, w


class FrameFit:
    """``robust_pose`` for one streamed frame against a fixed reference, the use mask's work done once.

    The check's fits (the plain one and, for 5-12 markers, each leave-one-out fit with 4 or more
    markers left) are linear in the centred observed points up to their rotations: every fit's Horn
    matrix N_j (Horn 1987 §4) is one prepared product with them (the reference centred per fit,
    times its weights, times ``solvers.rigid.HORN_MAP``), and every residual is linear in the top
    eigenvectors' outer products q_j q_j^T (the rotation entries, ``ROTATION_MAP``) plus a linear map
    of the points. A frame is one product, one batched ``eigh`` and two products, where the batched
    ``_fit_with_deleted`` takes some thirty array calls. A frame that fails the check starts IRLS from
    the same leave-one-out fit ``robust_pose`` picks (its fits' residuals at every marker: two more
    products) and iterates on the markers in use only. Same check, poses and weights as
    ``robust_pose`` to rounding; a top eigenvalue near double (degenerate geometry) goes to
    ``robust_pose`` itself.
    """

    CACHE = 64  # use masks kept (a stable set of <= 12 markers shows few; each costs ~30-140 µs to prepare)

    def __init__(self, reference: np.ndarray, iterations: int = 3, floor_mm: float = 1.0) -> None:
        self.reference = np.asarray(reference, dtype=np.float64)
        self.iterations = int(iterations)
        self.floor_mm = float(floor_mm)
        self._masks: dict[bytes, tuple] = {}
        k = len(self.reference)
        if 4 <= k <= LEAVE_ONE_OUT_MAX:  # every marker, and each one missing: ready before the first frame
            for use in np.concatenate([np.ones((1, k), bool), ~np.eye(k, dtype=bool)]):
                self._masks[use.tobytes()] = self._prepare(use)
        self._kept = len(self._masks)  # these stay; others leave first in, first out

    def _prepare(self, use: np.ndarray) -> tuple:
        k = len(use)
        left = np.flatnonzero(use)
        m = len(left)
        ref = self.reference[left]
        W = np.ones((1, m))
        if 5 <= k <= LEAVE_ONE_OUT_MAX and m >= 5:  # leaving one out leaves 4 or more
            W = np.concatenate([W, 1.0 - np.eye(m)])  # fit j + 1 leaves used marker j out
        J = len(W)
        Wn = W / W.sum(1, keepdims=True)
        A = ref[None] - (Wn @ ref)[:, None, :]  # (J, m, 3): the reference centred per fit
        Q = np.einsum("ji,jia,abn->jnib", W, A, HORN_MAP.reshape(3, 3, 16)).reshape(J * 16, 3 * m)
        # fit j's residual at used marker i: Z_j (on its own q_j q_j^T) + Wn_j @ centred points - centred point i
        Z = np.einsum("nca,jia->jnic", ROTATION_MAP.reshape(16, 3, 3), A)  # (J, 16, m, 3)
        # the check's residuals as two products: fit 0's at every marker, then each leave-one-out fit's at
        # its deleted marker
        Zc = np.zeros((J, 16, m + J - 1, 3))
        Zc[0, :, :m] = Z[0]
        Zc[np.arange(1, J), :, m + np.arange(J - 1)] = Z[np.arange(1, J), :, np.arange(J - 1)]
        Lc = np.concatenate([np.repeat(Wn[:1], m, 0), Wn[1:]])
        Lc[np.arange(m + J - 1), np.concatenate([np.arange(m), np.arange(J - 1)])] -= 1.0
        Lc = np.einsum("ri,cd->rcid", Lc, np.eye(3)).reshape(-1, 3 * m)
        maps = (Zc.reshape(J * 16, -1), Lc), Z.reshape(J, 16, 3 * m)
        w = use.astype(np.float64)
        w.setflags(write=False)
        return left, Wn, Q, maps, J, Wn @ ref, w

    def fit(self, pts: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """R, t and the per-marker weights for one frame: ``pts`` (k, 3), ``use`` (k,) bool, 3 or more set.

        Markers not in use may hold anything (NaN too): ``robust_pose`` sees them as zeros. The weights
        of a frame that passes the check are a shared read-only array.
        """
        if np.count_nonzero(use) < 3:
            return robust_pose(self.reference, np.where(use[:, None], pts, 0.0), use, self.iterations, self.floor_mm)
        key = use.tobytes()
        prep = self._masks.get(key)
        if prep is None:
            if len(self._masks) >= self.CACHE:
                del self._masks[next(itertools.islice(self._masks, self._kept, None))]
            prep = self._masks[key] = self._prepare(use)
        left, Wn, Q, ((Zc, Lc), Z), J, cs, w = prep
        m = len(left)
        P = pts if m == len(pts) else pts[left]
        kern = _KERNELS[0] if _KERNELS else _load_kernels()
        outcome, R0, t0, o, p, cb = kern.check_fit(P, Wn, Q, Zc, Lc, cs, ROTATION_MAP, CHECK_SCALES * self.floor_mm,
                                                    DEGENERATE)
        if outcome == kern.PASSED:
            return R0, t0, w
        if outcome == kern.DEGENERATE_TOP:
            return robust_pose(self.reference, np.where(use[:, None], pts, 0.0), use, self.iterations, self.floor_mm)
        R, t, wu = kern.refit(self.reference[left], P, o, p, cb, Wn, Z, cs, ROTATION_MAP, self.iterations,
                              self.floor_mm, TUKEY_C, MAD_TO_SIGMA)
        out = np.zeros(len(use))
        out[left] = wu
        return R, t, out


_KERNELS: list = []


def _load_kernels():
    """``solvers.rigid_kernels``, imported with the first streamed frame: offline use never loads numba."""
    from solvers import rigid_kernels

    _KERNELS.append(rigid_kernels)
    return rigid_kernels


def _irls(ref, pts, use, iterations, floor_mm, fits=None):
    """IRLS with Tukey's biweight from the leave-one-out start (Huber where Tukey keeps < 3)."""
    R, t = _initial(ref, pts, use, fits)
    w = use.astype(np.float64)
    for _ in range(iterations):
        r = _residuals(ref, pts, R, t)
        scale = np.maximum(MAD_TO_SIGMA * _masked_median(r, use), floor_mm)[..., None]
        u = r / (TUKEY_C * scale)
        tukey = np.where(use & (u < 1.0), (1.0 - u * u) ** 2, 0.0)
        huber = np.where(use, np.minimum(1.0, 1.0 / np.maximum(u, 1e-12)), 0.0)
        w = np.where(((tukey > 0).sum(-1) >= 3)[..., None], tukey, huber)
        R, t = kabsch(ref, pts, w)
    return R, t, w


class HeadStabiliser:
    """Remove head motion against a neutral reference of the markers (Seol §3.1, Curio §2.3).

    ``pose``/``stabilise`` work on one frame (n, 3) or a whole take (T, n, 3) at once; ``step``
    is the streaming form, which holds the last good pose through frames with too few markers.
    ``robust=False`` gives the plain Procrustes fit of the papers (for comparison).
    """

    def __init__(self, reference: np.ndarray, stable: np.ndarray, robust: bool = True, iterations: int = 3,
                 floor_mm: float = 1.0) -> None:
        self.reference = np.asarray(reference, dtype=np.float64)
        self.stable = np.asarray(stable, dtype=bool)
        if self.reference.shape != (len(self.stable), 3):
            raise ValueError(f"reference must be {len(self.stable)} x 3, got {self.reference.shape}")
        self.robust = bool(robust)
        self.iterations = int(iterations) if robust else 0
        self.floor_mm = float(floor_mm)
        self._stable_idx = np.flatnonzero(self.stable)
        self._stable_ref = self.reference[self._stable_idx]
        self._frame_fit = FrameFit(self._stable_ref, self.iterations, self.floor_mm) if self.iterations > 0 else None
        self.reset()

    def reset(self) -> None:
        """Forget the held pose (stream restarted)."""
        self._R = np.eye(3)
        self._t = np.zeros(3)
        self.weights = np.zeros(len(self.stable))  # last frame's per-marker weights (diagnostics)

    # ------------------------------------------------------------------ whole takes
    def _fit(self, ref, pts, use):
        if self.robust:
            R, t, w = robust_pose(ref, pts, use, self.iterations, self.floor_mm)
        else:
            R, t = kabsch(ref, pts, use)
            w = use.astype(np.float64)
        return R, t, w

    def pose_batch(self, positions: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Head rotation (T,3,3), translation (T,3) and a per-frame ``ok`` flag for a take.

        Frames with fewer than 3 stable markers use every visible marker; frames with fewer than 3
        visible markers at all take the pose of the nearest earlier good frame (or later, at the
        start) and are flagged not ok.
        """
        positions = np.asarray(positions, dtype=np.float64)
        valid = np.asarray(valid, dtype=bool)
        T = positions.shape[0]
        R = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
        t = np.zeros((T, 3))
        stable_ok = valid[:, self._stable_idx].sum(1) >= 3
        any_ok = valid.sum(1) >= 3
        fallback = ~stable_ok & any_ok
        if stable_ok.any():
            f = np.flatnonzero(stable_ok)
            k = self._stable_idx
            R[f], t[f], _ = self._fit(self._stable_ref, positions[f][:, k], valid[f][:, k])
        if fallback.any():
            f = np.flatnonzero(fallback)
            R[f], t[f], _ = self._fit(self.reference, positions[f], valid[f])
        if not any_ok.all() and any_ok.any():
            good = np.flatnonzero(any_ok)
            prev = np.maximum.accumulate(np.where(any_ok, np.arange(T), -1))
            src = np.where(prev >= 0, prev, good[0])
            R, t = R[src], t[src]
        return R, t, any_ok

    def pose(self, positions: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Head rotation and translation (head-to-world) for one frame (n, 3) or a take (T, n, 3)."""
        positions = np.asarray(positions, dtype=np.float64)
        if positions.ndim == 2:
            R, t, _ = self.pose_batch(positions[None], np.asarray(valid, bool)[None])
            return R[0], t[0]
        R, t, _ = self.pose_batch(positions, valid)
        return R, t

    def stabilise(self, positions: np.ndarray, valid: np.ndarray):
        """Stabilised positions (same shape, 0 where missing), rotation and translation."""
        R, t = self.pose(positions, valid)
        local = (np.asarray(positions, np.float64) - t[..., None, :]) @ R  # R^T applied per frame
        return np.where(np.asarray(valid, bool)[..., None], local, 0.0), R, t

    # ------------------------------------------------------------------ streams
    def step(self, positions: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One streamed frame: (stabilised (n, 3), R, t). Works on the stable subset only (k tiny
        SVDs), holds the last good pose when fewer than 3 markers are visible, never raises."""
        positions = np.asarray(positions, dtype=np.float64)
        valid = np.asarray(valid, dtype=bool)
        if not math.isfinite(positions.sum()):  # one reduction for the usual all-finite frame
            valid = valid & np.isfinite(positions).all(-1)
        sv = valid[self._stable_idx]
        if np.count_nonzero(sv) >= 3:
            if self._frame_fit is not None:
                R, t, w = self._frame_fit.fit(positions[self._stable_idx], sv)
            else:
                R, t, w = self._fit(self._stable_ref, positions[self._stable_idx], sv)
            self.weights.fill(0.0)
            self.weights[self._stable_idx] = w
        elif np.count_nonzero(valid) >= 3:
            R, t, w = self._fit(self.reference, np.where(valid[:, None], positions, 0.0), valid)
            self.weights = w
        else:
            R, t = self._R, self._t
            self.weights.fill(0.0)
        R, t = np.ascontiguousarray(R), np.ascontiguousarray(t)  # one compiled variant of unrotate
        self._R, self._t = R, t
        kern = _KERNELS[0] if _KERNELS else _load_kernels()
        return kern.unrotate(positions, valid, R, t), R.copy(), t.copy()


def smooth_pose(R: np.ndarray, t: np.ndarray, window: int, order: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Offline: Savitzky-Golay smoothing of a take's head pose (T, 3, 3), (T, 3) over ``window`` frames.

    Six stable markers with 0.5 mm noise leave about half a degree of frame-to-frame jitter in the
    Procrustes pose (Seol §3.1), which swings the chin by a millimetre; real head motion is far
    smoother than that at capture rates. Quaternions are sign-aligned frame to frame, filtered and
    renormalised. Streams cannot look ahead and keep the raw pose.
    """
    T = len(R)
    window = min(int(window), T if T % 2 else T - 1)
    if window % 2 == 0:
        window -= 1
    if window <= order:
        return R, t
    q = Rotation.from_matrix(R).as_quat()
    flip = np.concatenate([[1.0], np.sign(np.sum(q[1:] * q[:-1], axis=1))])
    q = q * np.cumprod(np.where(flip == 0, 1.0, flip))[:, None]
    qs = savgol(q, window, order)
    qs /= np.linalg.norm(qs, axis=1, keepdims=True)
    return Rotation.from_quat(qs).as_matrix(), savgol(t, window, order)


def savgol(x: np.ndarray, window: int, order: int) -> np.ndarray:
    """Savitzky-Golay smoothing along axis 0 (Savitzky & Golay 1964), as ``scipy.signal.savgol_filter``
    with its default ``mode="interp"``: the local polynomial fit's centre value inside, the fit to the
    first / last ``window`` samples at the ends. Here in numpy because importing scipy.signal costs a
    whole-take solve more (about 0.4-0.9 s) than the filtering itself. ``window`` odd, <= len(x)."""
    x = np.asarray(x, dtype=np.float64)
    half = window // 2
    A = np.vander(np.linspace(-1.0, 1.0, window), order + 1, increasing=True)  # centred, scaled: well conditioned
    fit = A @ np.linalg.pinv(A)  # window x window: samples -> the least-squares polynomial at each sample
    out = np.empty_like(x)
    inner = np.lib.stride_tricks.sliding_window_view(x, window, axis=0)  # (T - window + 1, ..., window)
    out[half:len(x) - half] = inner @ fit[half]
    out[:half] = np.tensordot(fit[:half], x[:window], axes=1)
    out[len(x) - half:] = np.tensordot(fit[window - half:], x[len(x) - window:], axes=1)
    return out


def head_pose_error(R: np.ndarray, t: np.ndarray, truth_R: np.ndarray, truth_t: np.ndarray,
                    reference: np.ndarray, truth_reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame rotation (degrees) and translation (mm) error of an estimated head pose.

    The stabilised frame is the frame of ``reference`` (the profile's source neutral), not the
    ground truth's head frame; both see the same neutral face, so the fixed rigid map A between
    them (``reference ~ A truth_reference``) is found once by Kabsch and composed in:
    raw = R (A x + a) + t must equal truth_R x + truth_t.
    """
    A, a = kabsch(truth_reference, reference)
    R_head = R @ A
    t_head = np.einsum("...ij,j->...i", R, a) + t
    dR = np.einsum("...ji,...jk->...ik", R_head, truth_R)
    cos = np.clip((np.trace(dR, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cos)), np.linalg.norm(t_head - truth_t, axis=-1)
