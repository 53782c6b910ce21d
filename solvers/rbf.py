"""Example-based expression blending with radial basis functions (Pyun et al. 2003 §3–4).

Key pairs: source key displacement vectors v_i (the actor's markers at a key expression, minus
the neutral; Eq. 1) and target key poses T_i (rig weights, or a mesh displacement, anything
blended linearly). Preparation, once:

* PCA of the key displacement vectors; eigenvectors with eigenvalue above a threshold form the
  feature matrix F (Eq. 2), parameters p_i = F v_i (Eq. 3);
* cardinal weight functions w_i(p) = sum_l a_il A_l(p) + sum_j r_ji R_j(p) (Eq. 4): the linear part
  [1, p] fitted to w_i(p_j) = delta_ij by least squares (Eq. 5), the residual interpolated exactly
  by R_j(p) = B(|p - p_j| / alpha_j), B the cubic B-spline, alpha_j the distance from key j to its
  nearest other key (Eqs. 6–8). w_i(p_j) = delta_ij holds exactly, so every key is reproduced.

Per frame: p = F d (Eq. 10), output = T_B + sum_i w_i(p) (T_i - T_B) (Eq. 11). Everything linear in
d is folded into one matrix at preparation, so a frame costs one projection, M distances, M
B-spline values and two small products. Missing markers: p is the least-squares fit of the visible
rows in feature space (F' p ~ d on visible rows), one small solve cached per visibility pattern.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np


def cubic_bspline(x: np.ndarray) -> np.ndarray:
    """Uniform cubic B-spline, C2, support |x| < 2, B(0) = 2/3 (Pyun Eq. 7's B)."""
    a = np.abs(x)
    t2 = np.maximum(2.0 - a, 0.0)
    t1 = np.maximum(1.0 - a, 0.0)
    return (t2 * t2 * t2 - 4.0 * (t1 * t1 * t1)) / 6.0  # (4 - 6a^2 + 3|a|^3)/6 inside |a| < 1


def feature_matrix(displacements: np.ndarray, threshold: float = 1e-5) -> np.ndarray:
    """F (Nbar x N): principal axes of the key displacement vectors (Pyun §3, Eq. 2).

    ``threshold`` is relative to the largest eigenvalue of the covariance (Pyun use an absolute
    1e-5 on their model's units; relative keeps the choice independent of mm vs m).
    """
    V = np.asarray(displacements, dtype=np.float64)
    centred = V - V.mean(axis=0)
    _, sv, Vt = np.linalg.svd(centred, full_matrices=False)
    eig = sv**2 / max(len(V) - 1, 1)
    if eig.size == 0 or eig[0] <= 0:
        raise ValueError("key displacement vectors are all identical: nothing to parameterise")
    keep = eig > threshold * eig[0]
    return Vt[keep].copy()


class RBFBlend:
    """Pyun et al. 2003 cardinal RBF weight functions over key pairs.

    ``source``: M x N key displacement vectors (N = 3 x markers, rows x0 y0 z0 x1 ...);
    ``target``: M x D key poses relative to the target base (rig weights, or mesh deltas).
    """

    def __init__(self, source: np.ndarray, target: np.ndarray, threshold: float = 1e-5,
                 cache_size: int = 32) -> None:
        V = np.asarray(source, dtype=np.float64)
        T = np.asarray(target, dtype=np.float64)
        if V.ndim != 2 or T.ndim != 2 or len(V) != len(T):
            raise ValueError(f"need M source keys (M x N) and M target poses (M x D), got {V.shape} and {T.shape}")
        if len(V) < 2:
            raise ValueError("need at least two keys")
        if not (np.isfinite(V).all() and np.isfinite(T).all()):
            raise ValueError("keys contain NaN or infinite values")
        self.M, self.N = V.shape
        self.F = feature_matrix(V, threshold)  # Nbar x N
        self.P = V @ self.F.T  # M x Nbar key parameters (Eq. 3)
        diff = np.linalg.norm(self.P[:, None, :] - self.P[None, :, :], axis=2)
        np.fill_diagonal(diff, np.inf)
        self.dilation = diff.min(axis=1)  # alpha_j: distance to the nearest other key
        if np.any(self.dilation <= 1e-12 * max(1.0, float(np.abs(self.P).max()))):
            i = int(np.argmin(self.dilation))
            j = int(np.argmin(diff[i]))
            raise ValueError(f"keys {i} and {j} coincide in feature space: the interpolant cannot be exact")
        # Linear part: w_i(p_j) = delta_ij fitted by least squares on A(p) = [1, p] (Eq. 5).
        X = np.hstack([np.ones((self.M, 1)), self.P])
        self.linear = np.linalg.lstsq(X, np.eye(self.M), rcond=None)[0]  # (Nbar+1) x M, column i = a_i
        residual = np.eye(self.M) - X @ self.linear  # w'_i(p_j), row j, column i (Eq. 6)
        np.fill_diagonal(diff, 0.0)
        Phi = cubic_bspline(diff / self.dilation[None, :])  # Phi[k, j] = R_j(p_k)
        try:
            self.radial = np.linalg.solve(Phi, residual)  # M x M, radial[j, i] = r_ji (Eq. 8)
        except np.linalg.LinAlgError:
            raise ValueError("radial system is singular (keys too close together); drop a key") from None
        self.target = T
        # Fold everything linear in d together: out = c0 + G d + K R(p) with p = F d.
        self._c0 = self.linear[0] @ T  # D
        G = (self.linear[1:] @ T).T @ self.F  # D x N
        self._FG = np.vstack([self.F, G])  # p and the linear part in one product
        self._nb = len(self.F)
        self._K = (self.radial @ T).T  # D x M
        self._Pn = np.sum(self.P**2, axis=1)
        self._inv_a = 1.0 / self.dilation
        self._masks: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self.cache_size = int(cache_size)

    def parameters(self, d: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """p = F d (Eq. 10); with rows missing, the least-squares p from the visible rows."""
        if rows is None or rows.all():
            return self.F @ d
        key = np.packbits(rows).tobytes()
        solve = self._masks.get(key)
        if solve is None:
            Fv = self.F[:, rows]
            reg = 1e-9 * np.trace(Fv @ Fv.T) / max(len(Fv), 1) + 1e-12
            solve = np.linalg.solve(Fv @ Fv.T + reg * np.eye(len(Fv)), Fv)  # Nbar x n_visible
            self._masks[key] = solve
            if len(self._masks) > self.cache_size:
                self._masks.popitem(last=False)
        else:
            self._masks.move_to_end(key)
        return solve @ d[rows]

    def key_weights(self, p: np.ndarray) -> np.ndarray:
        """w_i(p) for every key (Eq. 4)."""
        R = cubic_bspline(np.linalg.norm(p[None, :] - self.P, axis=1) / self.dilation)
        return self.linear[0] + p @ self.linear[1:] + R @ self.radial

    def evaluate(self, d: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Blended target (Eq. 11, relative to the target base) for a displacement vector ``d``."""
        if rows is not None and not rows.all():
            return self.key_weights(self.parameters(d, rows)) @ self.target
        y = self._FG @ d
        p = y[: self._nb]
        d2 = (p @ p) - 2.0 * (self.P @ p) + self._Pn  # |p - p_j|^2 with one product
        dist = np.sqrt(np.maximum(d2, 0.0)) * self._inv_a
        return self._c0 + y[self._nb:] + self._K @ cubic_bspline(dist)


class KeyBlendSolver:
    """The per-frame RBF mode: marker displacement in, blended rig weights out (Pyun §4).

    A neutral key (zero displacement <-> zero weights, Pyun's base model S_B <-> T_B) is added
    unless one is present, so the neutral face maps to the rest pose exactly.
    """

    def __init__(self, source: np.ndarray, target: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                 threshold: float = 1e-5, clip: bool = True) -> None:
        V = np.asarray(source, dtype=np.float64).reshape(len(source), -1)
        T = np.asarray(target, dtype=np.float64)
        if not np.any(np.all(np.abs(V) < 1e-12, axis=1)):
            V = np.vstack([np.zeros(V.shape[1]), V])
            T = np.vstack([np.zeros(T.shape[1]), T])
        self.blend = RBFBlend(V, T, threshold)
        self.lower = np.asarray(lower, dtype=np.float64)
        self.upper = np.asarray(upper, dtype=np.float64)
        self.clip = clip
        self.n = V.shape[1] // 3
        self.reset()

    def reset(self) -> None:
        self._last = np.clip(np.zeros(len(self.lower)), self.lower, self.upper)

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        d = np.asarray(target, dtype=np.float64).reshape(-1)
        seen = np.asarray(valid, dtype=bool).reshape(-1)
        if d.shape[0] != 3 * self.n or seen.shape[0] != self.n:
            return self._last.copy()
        if seen.all() and np.isfinite(d).all():  # the common frame: no masking work at all
            with np.errstate(all="ignore"):
                w = self.blend.evaluate(d)
            if np.isfinite(w).all():
                self._last = np.clip(w, self.lower, self.upper) if self.clip else w
            return self._last.copy()
        rows = np.repeat(np.asarray(valid, dtype=bool).reshape(self.n), 3) & np.isfinite(d)
        if not rows.any():
            return self._last.copy()
        d = np.where(rows, d, 0.0)
        with np.errstate(all="ignore"):
            w = self.blend.evaluate(d, rows)
        if not np.all(np.isfinite(w)):
            return self._last.copy()
        if self.clip:
            w = np.clip(w, self.lower, self.upper)
        self._last = w
        return w.copy()
