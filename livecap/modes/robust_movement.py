"""Noise-robust offline movement matching: the `movement` mode's offline solve on a tuned profile.

Plain movement matching (Seol et al. 2012 §4, Eq. 2) matches the markers' velocities, so on
noisy markers it reproduces the noise's velocity, and its PCA shapes prior (§5) is a uniform
pull that shrinks blinks (docs/movement.md, docs/robustness.md). This solve keeps Seol's
objective and sets every weight from the noise estimate that ``livecap.modes.robust.tune_profile``
stores in ``profile.settings["robust"]`` (sigma per coordinate, mm):

1. markers smoothed zero-phase by the centred quadratic over ``2 lag + 1`` frames
   (``solvers.filters.FixedLagSmoother.filter``, ``lag`` the robust default 4): the velocity term
   then matches the motion, and the noise left has variance ``sigma^2 sum(h^2)``;
2. beta (Sobolev position term, §7.1) by inverse-variance weighting of the two residuals: after
   the smoother h, position noise has variance ``sigma^2 sum(h^2)`` and velocity noise
   ``sigma^2 sum(diff(h)^2)``; weighting each term by its inverse variance and normalising the
   velocity term to 1 gives ``beta = sum(diff(h)^2) / sum(h^2)`` (0.373 for lag 4; 2 on raw
   markers). beta > 0 is also what stops drift;
3. no PCA prior (alpha 0): plausibility comes from an L1 term on the non-negative weights
   (Lewis et al. 2014 §5.2), ``mu_k = beta * 2 z sigma' |b_k|`` with sigma' the smoothed noise and
   z = sqrt(2 ln m) (``solvers.sparse_fit``): the same threshold as the sparse per-frame fit,
   scaled by beta because the L1 competes with the position term (in a steady state of the
   decoupled problem an active shape sits at ``y - mu / (2 beta |b|^2)``, i.e. z sigma' / |b_k|
   below its own fit, as in the per-frame fit);
4. the limits as constraints (``limits="bound"``: ``solvers.bounded.BoundedMovement``), so
   resting shapes are exactly 0 instead of noise;
5. optionally (``reweight`` > 0, default 0) reweighted L1 (Candes, Wakin & Boyd 2008, "Enhancing
   sparsity by reweighted l1 minimization"): re-solve with ``mu eps / (w + eps)``, eps the L1
   offset in weight units ``mu_k / (2 beta |b_k|^2)``, which removes the lasso's shrinkage of
   active shapes (blinks) but also lets model error grow spurious sustained shapes
   (docs/robustness.md has both measured);
6. the solved curves l1-trend-filtered (``solvers.trend``, Kim, Koh, Boyd & Gorinevsky 2009 §2):
   ``min |w - x|^2 / 2 + lam_k |D2 x|_1`` per shape with ``lam_k = trend * s_k``, ``s_k = sigma' /
   |b_k|`` the shape's weight noise sd and ``trend`` 10 (``livecap.modes.robust.RobustSettings``):
   piecewise-linear curves whose kinks are where the data put them, so the noise's second
   differences go while blink onsets and peaks stay (a quadratic smoother of that strength shaves
   peaks); fixed frames restored afterwards.

``MovementMatching`` itself stays the plain solver; this class wraps one.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from livecap.modes.robust import RobustSettings
from solvers.filters import FixedLagSmoother, savgol_weights
from solvers.movement import Edit, MovementMatching, edit_region
from solvers.sparse_fit import l1_weights, universal_threshold
from solvers.trend import TrendFilter

log = logging.getLogger(__name__)
BOUND_TOL = 1e-4  # ADMM residuals, weight units: far below a weight's noise sd (~0.01-0.05)


def smoother_beta(lag: int) -> float:
    """Inverse-variance ratio velocity / position of white noise after the centred quadratic over 2 lag + 1."""
    h = savgol_weights(int(lag))
    return float(np.sum(np.diff(np.r_[0.0, h, 0.0]) ** 2) / np.sum(h**2))


class RobustMovement:
    """Offline: smooth markers -> bounded movement matching with an L1 term -> trend-filter weights.

    ``inner`` is the plain :class:`MovementMatching` (alpha 0, beta from the smoother, bounded
    limits); ``noise_mm`` the raw marker noise sigma; ``lag`` the smoother half-width (frames);
    ``trend`` the weight trend filter's penalty in weight noise sds (0: none); ``reweight`` the number of
    reweighted-L1 re-solves; ``l1`` False drops the L1 term (when ``inner`` carries an animation prior instead).
    ``live`` makes the streamed form ``step`` runs (:class:`StreamedMovement`), on its first use: an offline
    solve never steps, so it does not build the marker filter, the fit and the weight filter.
    """

    def __init__(self, inner: MovementMatching, noise_mm: float, lag: int = RobustSettings.lag,
                 trend: float = RobustSettings.trend, z: float | None = None, reweight: int = 0,
                 l1: bool = True, *, live: Callable[[], StreamedMovement]) -> None:
        self.inner = inner
        self._make_live, self._live = live, None
        self.lower, self.upper = inner.lower, inner.upper
        self.lag = int(lag)
        self.smoother = FixedLagSmoother(self.lag)
        B = inner.blocks.basis
        gain = float(np.sum(savgol_weights(self.lag) ** 2))
        self.trend = TrendFilter.for_basis(B, noise_mm * np.sqrt(gain), trend) if trend > 0 else None
        zz = universal_threshold(B.shape[1]) if z is None else float(z)
        scale = inner.blocks.beta if inner.blocks.beta > 0 else 1.0
        self.noise_mm = float(noise_mm)
        self.mu = scale * l1_weights(B, self.noise_mm * np.sqrt(gain), zz) * float(l1)
        self.eps = self.mu / (2.0 * scale * np.maximum(np.sum(B**2, axis=0), 1e-12))  # L1 offset, weight units
        self.reweight = int(reweight)

    def smooth(self, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
        S = np.asarray(targets, dtype=np.float64)
        S = S.reshape(len(S), -1, 3)
        return self.smoother.filter(S, np.broadcast_to(np.asarray(valid, bool)[..., None], S.shape))

    def solve(self, targets: np.ndarray, valid: np.ndarray | None = None,
              fixed: Mapping[int, np.ndarray] | None = None) -> np.ndarray:
        S = np.asarray(targets, dtype=np.float64)
        S = S.reshape(len(S), -1, 3)
        valid = np.ones(S.shape[:2], dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
        if len(S) == 0:
            return self.inner.solve(S, valid, fixed)
        smoothed = self.smooth(S, valid)
        W = self.inner.solve(smoothed, valid, fixed, linear=self.mu)
        for _ in range(self.reweight if self.mu.any() else 0):
            W = self.inner.solve(smoothed, valid, fixed, linear=self.mu * self.eps / (np.maximum(W, 0.0) + self.eps))
        if self.trend is not None and len(W) > 2:
            W = np.clip(self.trend.filter(W), self.lower, self.upper)
            if not self.trend.converged:
                log.warning("weight trend filter stopped at %d iterations before its tolerance %.1g",
                            self.trend.iterations, self.trend.tol)
            for f, w in self.inner.boundary_frames(smoothed, valid, fixed).items():
                W[f] = w
        return W

    def edit(self, weights: np.ndarray, edits: Sequence[Edit], targets: np.ndarray | None = None,
             valid: np.ndarray | None = None) -> np.ndarray:
        """Seol §6 edits, re-solved against the smoothed source markers (or the last solve's) under the
        solve's own L1 term, so resting shapes inside the range stay at rest; the re-solved frames are
        then trend-filtered like the solve's, keys and range ends fixed, so the range is as smooth as
        the curves around it."""
        if targets is not None:
            v = np.ones(np.shape(targets)[:2], bool) if valid is None else np.asarray(valid, bool)
            targets = self.smooth(targets, v)
        E = self.inner.edit(weights, edits, targets, valid, linear=self.mu)
        if self.trend is None:
            return E
        free = edit_region(edits, len(E))
        if not free.any():
            return E
        idx = np.flatnonzero(free)
        seg = slice(max(idx[0] - 2, 0), min(idx[-1] + 3, len(E)))  # two fixed frames each side carry the slope in
        filtered = np.clip(self.trend.filter(E[seg], fixed=~free[seg]), self.lower, self.upper)
        E[seg] = np.where(free[seg, None], filtered, E[seg])
        return E

    @property
    def live(self) -> StreamedMovement:
        if self._live is None:
            self._live = self._make_live()
        return self._live

    @property
    def latency_frames(self) -> int:
        """Frames ``step`` trails its input (a live session pairs each frame by it)."""
        return self.live.latency_frames

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        return self.live.step(target, valid)

    def reset(self) -> None:
        self.inner.reset()
        if self._live is not None:
            self._live.reset()


class StreamedMovement:
    """Live movement: filtered markers -> one movement step a frame against the previous frame (issues 35 / 41).

    Seol's sliding window (§4-5, ``solvers.streaming``) with a free right end and no prior term (the noise-robust
    solve's alpha 0) publishes the per-frame least-squares fit of the raw markers: there the velocity and position
    residuals are both at their minimum, so the movement term removes no noise, and the limits are a clip of that
    fit (docs/robustness.md "Streamed movement": jitter 140-415 x truth). Here the noise goes first, in a causal
    marker filter (``markers``: ``step(x, valid) -> (x', valid')``, its ``lag`` the latency); each frame then
    minimises Seol's objective with the previous frame's solve w' as the fixed left boundary (K = 1),

        |B (w - w') - (x - x')|^2 + beta |B w - x|^2 + mu^T w,   lower <= w <= upper,

    i.e. ``(1 + beta) |B w - y|^2 + mu^T w`` with ``y = (B w' + (x - x') + beta x) / (1 + beta)``: the bounded
    sparse fit (``fit``, hysteresis L1 of ``solvers.sparse_fit`` at the filtered noise) of y. A marker missing in
    either frame has no movement: its row of y is x. ``weight_filter`` (the robust modes' IMM) smooths the output.
    """

    def __init__(self, basis: np.ndarray, markers, fit, beta: float, weight_filter=None) -> None:
        self.B = np.asarray(basis, dtype=np.float64)
        self.markers, self.fit, self.beta, self.weight_filter = markers, fit, float(beta), weight_filter
        self.lower, self.upper = fit.lower, fit.upper
        self.reset()

    @property
    def latency_frames(self) -> int:
        return int(getattr(self.markers, "lag", 0))

    def reset(self) -> None:
        self.markers.reset()
        self.fit.reset()
        if self.weight_filter is not None:
            self.weight_filter.reset()
        self._x: np.ndarray | None = None
        self._ok: np.ndarray | None = None
        self._w: np.ndarray | None = None
        self._y = np.empty(self.B.shape[0])
        self._d = np.empty(self.B.shape[0])

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        x, ok = self.markers.step(target, valid)
        x = x.reshape(-1)
        y = x
        if self._w is not None:
            y, d = self._y, self._d
            np.dot(self.B, self._w, out=y)
            y += np.subtract(x, self._x, out=d)
            y += np.multiply(self.beta, x, out=d)
            y /= 1.0 + self.beta
            moved = ok & self._ok
            if not moved.all():
                gone = np.repeat(~moved, 3)
                y[gone] = x[gone]
        w = self.fit.step(y, ok)  # a new array: kept as w' as it is
        self._x, self._ok, self._w = x, ok, w
        if self.weight_filter is not None:
            w = self.weight_filter.step(w)
            np.clip(w, self.lower, self.upper, out=w)
        return w
