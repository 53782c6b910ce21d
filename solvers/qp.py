"""Per-frame bounded quadratic programme for blendshape weights (Curio et al. 2006 §2.3).

Curio et al. fit each frame's markers by "quadratic programming enforcing positivity constraints
on the morph weights"; Lewis et al. 2014 §5.2 note this is the standard constrained linear problem
for mocap-driven rigs. Per frame:

    minimise  |M (B w - s)|^2 + lam |w|^2 + gam |w - w_prev|^2 + alpha (w - mu)' P (w - mu)
    subject to lower <= w <= upper,

M a per-marker weight (confidence), the last two terms an optional temporal term and Gaussian
prior. The Hessian H = B'M^2B + (lam + gam) I + alpha P is constant, so each marker-visibility
pattern gets one DAQP workspace (H factored once; only the linear term changes per frame) and
the previous frame's active set warm-starts the next: DAQP won benchmarks/qp_libraries.py.
Missing markers drop their rows; workspaces are cached per visibility pattern in a bounded LRU.
"""

from __future__ import annotations

import logging
from collections import OrderedDict

import numpy as np

log = logging.getLogger(__name__)

_ACTIVE, _LOWER = 1, 2  # DAQP constraint state bits (sense): active, at the lower bound


class FrameQP:
    """Streaming per-frame QP. ``step(target (n,3), valid (n,)) -> weights (m,)``; never raises."""

    def __init__(self, basis: np.ndarray, lower: np.ndarray, upper: np.ndarray, ridge: float = 0.0,
                 temporal: float = 0.0, marker_weights: np.ndarray | None = None,
                 prior: tuple[np.ndarray, np.ndarray] | None = None, prior_weight: float = 0.0,
                 cache_size: int = 32) -> None:
        import daqp

        self._daqp = daqp
        self.basis = np.asarray(basis, dtype=np.float64)
        if self.basis.ndim != 2 or self.basis.shape[0] % 3:
            raise ValueError(f"basis must be 3n x m, got {self.basis.shape}")
        self.n, self.m = self.basis.shape[0] // 3, self.basis.shape[1]
        self.lower = np.asarray(lower, dtype=np.float64).reshape(self.m)
        self.upper = np.asarray(upper, dtype=np.float64).reshape(self.m)
        if np.any(self.lower > self.upper):
            raise ValueError("lower bound above upper bound")
        if ridge < 0 or temporal < 0 or prior_weight < 0:
            raise ValueError("ridge, temporal and prior weights must be >= 0")
        self.ridge, self.temporal = float(ridge), float(temporal)
        mw = np.ones(self.n) if marker_weights is None else np.asarray(marker_weights, dtype=np.float64)
        if mw.shape != (self.n,) or np.any(mw < 0) or not np.isfinite(mw).all():
            raise ValueError(f"marker_weights must be {self.n} finite values >= 0")
        self._row_w = np.repeat(mw**2, 3)  # M^2 on the rows x0 y0 z0 x1 ...
        self._BtD = (self.basis * self._row_w[:, None]).T.copy()  # m x 3n, B'M^2
        self._const = (self.ridge + self.temporal) * np.eye(self.m)
        self._prior_f = np.zeros(self.m)
        if prior is not None and prior_weight > 0:
            mu, P = (np.asarray(a, dtype=np.float64) for a in prior)
            self._const = self._const + prior_weight * P
            self._prior_f = prior_weight * P @ mu
        # Unobserved shapes (all their markers missing) make H singular; a tiny pull towards the
        # previous weights keeps it positive definite and holds those shapes where they were.
        scale = float(np.mean(np.einsum("ij,ij->j", self.basis, self.basis))) or 1.0
        self._floor = 1e-9 * scale
        self.linear = np.zeros(self.m)  # a linear term callers may change per frame (e.g. an L1 penalty)
        self.cache_size = int(cache_size)
        self._models: OrderedDict[bytes, tuple] = OrderedDict()
        self.failures = 0
        self.iterations = 0  # active-set iterations of the last solve (warm starts keep this small)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        self._prev = np.clip(np.zeros(self.m), self.lower, self.upper)
        self._lam: np.ndarray | None = None  # multipliers of the last solve: its active set
        self._last_key: bytes | None = None

    def _active_set(self) -> np.ndarray:
        """DAQP constraint states from the last multipliers: active, and at which bound."""
        if self._lam is None:
            return np.zeros(self.m, dtype=np.int32)
        lam = self._lam
        return np.where(lam != 0, _ACTIVE | np.where(lam < 0, _LOWER, 0), 0).astype(np.int32)

    @property
    def cached_patterns(self) -> int:
        return len(self._models)

    def _workspace(self, key: bytes, seen: np.ndarray):
        ws = self._models.get(key)
        if ws is not None:
            self._models.move_to_end(key)
            return ws
        rows = np.repeat(seen, 3)
        Bv = self.basis[rows]
        H = Bv.T @ (Bv * self._row_w[rows, None]) + self._const
        floor = 0.0
        try:  # (max / min Cholesky diagonal)^2 bounds cond(H) from below: no SVD per new pattern
            d = np.diagonal(np.linalg.cholesky(H))
            if d.min() <= 0 or (d.max() / d.min()) ** 2 > 1e12:
                raise np.linalg.LinAlgError
        except np.linalg.LinAlgError:
            floor = self._floor
            H = H + floor * np.eye(self.m)
        BtD = self._BtD if rows.all() else self._BtD * rows[None, :]
        model = self._daqp.Model()
        model.setup(H, np.zeros(self.m), np.zeros((0, self.m)), self.upper.copy(), self.lower.copy())
        ws = (model, BtD, floor, H, None if seen.all() else rows)
        self._models[key] = ws
        if len(self._models) > self.cache_size:
            self._models.popitem(last=False)
        return ws

    # ------------------------------------------------------------------ per frame
    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        s = np.asarray(target, dtype=np.float64).reshape(-1)
        seen = np.asarray(valid, dtype=bool).reshape(-1)
        if s.shape[0] != 3 * self.n or seen.shape[0] != self.n:
            log.warning("frame has %d coordinates / %d flags, expected %d markers: holding the last weights",
                        s.shape[0], seen.shape[0], self.n)
            return self._prev.copy()
        if not np.isfinite(s).all():
            seen = seen & np.isfinite(s.reshape(self.n, 3)).all(axis=1)
        if not seen.any():
            return self._prev.copy()
        key = seen.tobytes()
        model, BtD, floor, H, rows = self._workspace(key, seen)
        if rows is not None:
            s = np.where(rows, s, 0.0)
        f = -(BtD @ s) - self._prior_f + self.linear
        if self.temporal + floor > 0:
            f -= (self.temporal + floor) * self._prev
        try:
            if key == self._last_key:  # the workspace still holds last frame's active set
                model.update(f=f)
            else:  # another visibility pattern: hand it the active set we just left
                model.update(f=f, sense=self._active_set())
            x, _, flag, info = model.solve()
            ok = flag > 0 and np.isfinite(x).all()
        except Exception as exc:  # noqa: BLE001 - a stream must survive a solver failure
            log.debug("daqp failed: %s", exc)
            ok = False
        if ok:
            self._last_key = key
            self._lam = info["lam"]
            self.iterations = int(info["iterations"])
        else:
            self.failures += 1
            self._last_key = None
            x = np.clip(np.linalg.lstsq(H, -f, rcond=None)[0], self.lower, self.upper)
            if not np.all(np.isfinite(x)):
                x = self._prev.copy()
            self._lam = None
        self._prev = np.minimum(np.maximum(x, self.lower), self.upper)  # DAQP's tolerance, not a clip
        return self._prev.copy()
