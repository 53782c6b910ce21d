"""Rigid and similarity fits between corresponding point sets (Arun et al. 1987; Umeyama 1991).

Shared by head stabilisation (Seol et al. 2012 §3.1), calibration's proportion matching (§3.2),
rig transfer and the viewer's placement of the rig in the actor's head frame.

Batches of fits take the rotation in closed form from the cross-covariance (Horn 1987, "Closed-form
solution of absolute orientation using unit quaternions", JOSA A 4: 629, §4-5: the quaternion is the
top eigenvector of a symmetric 4 x 4 matrix; its eigenvalue found by Newton's method on the
characteristic quartic from the upper bound (G_a + G_b) / 2, as in Theobald 2005, Acta Cryst. A61:
478, Eqs. 5-10). Every step is elementwise over the batch, so a take's frames cost tens of
nanoseconds each instead of one LAPACK SVD call (~4 µs) apiece; the result is the SVD's proper
rotation (the reflection guard is built in: quaternions are rotations). Near-degenerate fits (the
top eigenvalue nearly double: collinear points, no weight) go to the SVD.
"""

from __future__ import annotations

import numpy as np

SMALL_BATCH = 48  # below this many fits one LAPACK eigh call beats the elementwise Newton
NEWTON_MAX = 12  # from the bound a good fit converges in 2-4 steps; slower rows (double roots) go to the SVD
DEGENERATE = 1e-9  # adjugate diagonal below this x the scale^3: top eigenvalue not simple


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising sum w_i |R src_i + t - dst_i|^2 (never a reflection).

    ``src``/``dst`` may be batched: (..., k, 3); ``weights`` (..., k). All-zero weights give the
    identity rotation rather than NaN.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    w = np.ones(src.shape[:-1]) if weights is None else np.asarray(weights, dtype=np.float64)
    if src.ndim == 2 and dst.ndim == 2 and w.ndim == 1:
        return _kabsch_one(src, dst, w)
    wk = w[..., None]
    wsum = np.maximum(w.sum(-1), 1e-300)[..., None]
    cs = (wk * src).sum(-2) / wsum  # elementwise sums: numpy's batched matmul is slow on 3-wide stacks
    cd = (wk * dst).sum(-2) / wsum
    a = src - cs[..., None, :]
    b = dst - cd[..., None, :]
    wb = wk * b
    H = (a[..., :, None] * wb[..., None, :]).sum(-3)
    bound = 0.5 * ((wk * a * a).sum((-1, -2)) + (wb * b).sum((-1, -2)))
    R = rotation_from_covariance(H, bound)
    t = cd - (R * cs[..., None, :]).sum(-1)
    return R, t


def rotation_from_covariance(H: np.ndarray, bound: np.ndarray | None = None) -> np.ndarray:
    """The Kabsch rotation (R a ~ b) of cross-covariances H = sum w a b^T (..., 3, 3), batched.

    Horn 1987 §4-5: the rotation's quaternion is the top eigenvector of the symmetric 4 x 4 matrix
    N(H). Small batches (a streamed frame's fits) take it from one LAPACK ``eigh`` call; large ones
    (a take) by Newton's method on N's characteristic quartic started at ``bound`` = (sum w|a|^2 +
    sum w|b|^2) / 2, an upper bound on the top eigenvalue (Theobald 2005 Eqs. 5-10), and the
    eigenvector from the adjugate of N - lambda I, elementwise over the batch.
    """
    H = np.asarray(H, dtype=np.float64)
    lead = H.shape[:-2]
    flat = H.reshape(-1, 9)
    if len(flat) < SMALL_BATCH or bound is None:
        R, bad = _rotation_eigh(flat)
    else:
        R, bad = _rotation_newton(flat, np.asarray(bound, dtype=np.float64).reshape(-1))
    if bad.any():
        R[bad] = _svd_rotation(flat[bad].reshape(-1, 3, 3))
    return R.reshape(*lead, 3, 3)


# Horn's N as a linear map of H's 9 entries (Sxx Sxy Sxz Syx Syy Syz Szx Szy Szz) -> N's 16 (public: the
# streamed head fit folds it into its own prepared products)
HORN_MAP = np.zeros((9, 16))
for _row, _col, _entries in (
        (0, 0, "+xx +yy +zz"), (0, 1, "+yz -zy"), (0, 2, "+zx -xz"), (0, 3, "+xy -yx"),
        (1, 1, "+xx -yy -zz"), (1, 2, "+xy +yx"), (1, 3, "+zx +xz"),
        (2, 2, "-xx +yy -zz"), (2, 3, "+yz +zy"), (3, 3, "-xx -yy +zz")):
    for _e in _entries.split():
        _k = 3 * "xyz".index(_e[1]) + "xyz".index(_e[2])
        HORN_MAP[_k, 4 * _row + _col] += 1.0 if _e[0] == "+" else -1.0
        if _row != _col:
            HORN_MAP[_k, 4 * _col + _row] += 1.0 if _e[0] == "+" else -1.0
# rotation matrix entries as a linear map of the quaternion's outer product q q^T (q = w, x, y, z)
ROTATION_MAP = np.zeros((16, 9))
for _k, _terms in enumerate(("+ww +xx -yy -zz", "+xy +xy -wz -wz", "+xz +xz +wy +wy",
                             "+xy +xy +wz +wz", "+ww -xx +yy -zz", "+yz +yz -wx -wx",
                             "+xz +xz -wy -wy", "+yz +yz +wx +wx", "+ww -xx -yy +zz")):
    for _e in _terms.split():
        ROTATION_MAP[4 * "wxyz".index(_e[1]) + "wxyz".index(_e[2]), _k] += 1.0 if _e[0] == "+" else -1.0


HORN_MAP.setflags(write=False)
ROTATION_MAP.setflags(write=False)


def _quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """(B, 4) unit quaternions (w, x, y, z) -> (B, 3, 3)."""
    return ((q[:, :, None] * q[:, None, :]).reshape(-1, 16) @ ROTATION_MAP).reshape(-1, 3, 3)


def _rotation_eigh(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ev, V = np.linalg.eigh((flat @ HORN_MAP).reshape(-1, 4, 4))
    scale = np.abs(ev).max(-1)
    bad = ~(ev[:, 3] - ev[:, 2] > DEGENERATE * scale)
    return _quaternion_to_rotation(V[:, :, 3]), bad


def _rotation_newton(flat: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    S = flat.T
    sxx, sxy, sxz, syx, syy, syz, szx, szy, szz = S
    n00, n11, n22, n33 = sxx + syy + szz, sxx - syy - szz, syy - sxx - szz, szz - sxx - syy
    n01, n02, n03 = syz - szy, szx - sxz, sxy - syx
    n12, n13, n23 = sxy + syx, szx + sxz, syz + szy
    # characteristic polynomial of the traceless N: x^4 + c2 x^2 + c1 x + c0
    c2 = -2.0 * np.einsum("ib,ib->b", S, S)
    c1 = -8.0 * (sxx * (syy * szz - syz * szy) - sxy * (syx * szz - syz * szx) + sxz * (syx * szy - syy * szx))
    c0 = _det4(n00, n01, n02, n03, n11, n12, n13, n22, n23, n33)
    lam = bound.copy()
    for _ in range(NEWTON_MAX):
        lam2 = lam * lam
        p = (lam2 + c2) * lam2 + c1 * lam + c0
        dp = 4.0 * lam2 * lam + 2.0 * c2 * lam + c1
        step = np.divide(p, dp, out=np.zeros_like(p), where=dp > 0)
        lam -= step
        moving = np.abs(step) > 1e-14 * np.abs(lam)
        if not moving.any():
            break
    adj = _adjugate4(n00 - lam, n01, n02, n03, n11 - lam, n12, n13, n22 - lam, n23, n33 - lam)  # 4 x 4 x B
    diag = -np.stack([adj[0, 0], adj[1, 1], adj[2, 2], adj[3, 3]])  # adj = (product of 3 negative gaps) q q^T
    col = np.argmax(diag, axis=0)
    q = np.take_along_axis(adj, col[None, None, :], axis=1)[:, 0].T  # B x 4, along the eigenvector
    q /= np.sqrt(np.maximum(np.einsum("bi,bi->b", q, q), 1e-300))[:, None]
    scale = np.maximum(np.abs(lam), np.sqrt(np.maximum(-0.5 * c2, 0.0)))
    top = np.take_along_axis(diag, col[None], 0)[0]
    return _quaternion_to_rotation(q), moving | ~(top > DEGENERATE * scale**3)


def _det4(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33):
    """Determinant of symmetric 4 x 4 matrices given by their upper triangles (elementwise)."""
    return _adjugate4(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, det_only=True)


def _adjugate4(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, det_only: bool = False):
    """Adjugate (4, 4, B) of symmetric 4 x 4 matrices from 2 x 2 minors (Laplace by row pairs)."""
    a10, a20, a30, a21, a31, a32 = a01, a02, a03, a12, a13, a23
    s0 = a00 * a11 - a10 * a01
    s1 = a00 * a12 - a10 * a02
    s2 = a00 * a13 - a10 * a03
    s3 = a01 * a12 - a11 * a02
    s4 = a01 * a13 - a11 * a03
    s5 = a02 * a13 - a12 * a03
    c5 = a22 * a33 - a32 * a23
    c4 = a21 * a33 - a31 * a23
    c3 = a21 * a32 - a31 * a22
    c2 = a20 * a33 - a30 * a23
    c1 = a20 * a32 - a30 * a22
    c0 = a20 * a31 - a30 * a21
    if det_only:
        return s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0
    return np.array([
        [a11 * c5 - a12 * c4 + a13 * c3, -a01 * c5 + a02 * c4 - a03 * c3,
         a31 * s5 - a32 * s4 + a33 * s3, -a21 * s5 + a22 * s4 - a23 * s3],
        [-a10 * c5 + a12 * c2 - a13 * c1, a00 * c5 - a02 * c2 + a03 * c1,
         -a30 * s5 + a32 * s2 - a33 * s1, a20 * s5 - a22 * s2 + a23 * s1],
        [a10 * c4 - a11 * c2 + a13 * c0, -a00 * c4 + a01 * c2 - a03 * c0,
         a30 * s4 - a31 * s2 + a33 * s0, -a20 * s4 + a21 * s2 - a23 * s0],
        [-a10 * c3 + a11 * c1 - a12 * c0, a00 * c3 - a01 * c1 + a02 * c0,
         -a30 * s3 + a31 * s1 - a32 * s0, a20 * s3 - a21 * s1 + a22 * s0],
    ])


def _svd_rotation(H: np.ndarray) -> np.ndarray:
    """Kabsch rotation of covariances (..., 3, 3) by SVD with the reflection guard (Arun 1987)."""
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    Vt[..., 2, :] *= np.where(d == 0, 1.0, d)[..., None]  # reflection guard: flip the smallest axis
    return np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)


def _kabsch_one(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Single-frame Kabsch with few numpy calls (the streaming path)."""
    ws = w.sum()
    if ws <= 0:
        return np.eye(3), np.zeros(3)
    cs = (w @ src) / ws
    cd = (w @ dst) / ws
    H = (src - cs).T @ ((dst - cd) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    R = Vt.T @ U.T
    if np.linalg.det(R) < 0:  # reflection guard: flip the axis of the smallest singular value
        Vt[2] = -Vt[2]
        R = Vt.T @ U.T
    return R, cd - R @ cs


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale, rotation, translation with s R src + t ~ dst (Umeyama 1991)."""
    R, _ = kabsch(src, dst)
    cs, cd = src.mean(0), dst.mean(0)
    s = np.sum((dst - cd) * ((src - cs) @ R.T)) / np.sum((src - cs) ** 2)
    return float(s), R, cd - s * R @ cs
