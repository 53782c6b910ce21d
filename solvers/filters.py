"""Low-latency filters for noisy marker and weight channels.

* ``OneEuroFilter``: the 1€ filter of Casiez, Roussel & Vogel, "1€ Filter: A Simple Speed-based
  Low-pass Filter for Noisy Input in Interactive Systems", CHI 2012 (§"The 1€ filter" and its
  pseudo-code). An exponential smoother whose cutoff rises with the signal's speed: while a
  channel is still, a low cutoff removes jitter; when it moves, a high cutoff removes lag.
  Per sample, with Te the sampling period::

      alpha(fc) = 1 / (1 + tau / Te),   tau = 1 / (2 pi fc)
      dx      = (x - x_prev_raw) / Te                 (raw derivative)
      dx_hat  = alpha(d_cutoff) dx + (1 - alpha(d_cutoff)) dx_hat_prev
      fc      = min_cutoff + beta |dx_hat|
      x_hat   = alpha(fc) x + (1 - alpha(fc)) x_hat_prev

  Vectorised over channels (markers x 3 or shapes); ``min_cutoff``, ``beta`` and ``d_cutoff``
  are scalars or one value per channel. Causal: the added lag is the exponential smoother's
  time constant tau, shrinking as the channel speeds up.
* ``CausalPolyFilter``: the causal end of a Savitzky–Golay fit (a quadratic through the last N
  samples, evaluated at the newest): no lag on motion up to constant acceleration, noise variance
  cut by ``noise_gain`` (0.55 for N = 12). Used on the markers before the robust solve.
* ``FixedLagSmoother``: a local quadratic (Savitzky–Golay) fit over a centred window of
  ``2 lag + 1`` frames; output frame t - lag, so its latency is exactly ``lag`` frames. For
  offline solves and streaming modes that may look ahead (Seol et al. 2012 §6 "lookahead").

Both accept a valid mask: a missing sample leaves a channel's state untouched (no NaN ever in
the output), and a channel that was missing for longer than ``reinit_after`` frames restarts
from its first new sample instead of blending with a stale estimate.
"""

from __future__ import annotations

import numpy as np


def smoothing_factor(cutoff: np.ndarray | float, period: float) -> np.ndarray:
    """alpha = 1 / (1 + tau / Te) with tau = 1 / (2 pi fc) (Casiez et al. 2012, Eq. for alpha)."""
    tau = 1.0 / (2.0 * np.pi * np.asarray(cutoff, dtype=np.float64))
    return 1.0 / (1.0 + tau / period)


class OneEuroFilter:
    """The 1€ filter over a vector of channels; ``step(x, valid)`` returns the filtered vector."""

    def __init__(self, rate: float, min_cutoff: float | np.ndarray = 1.0, beta: float | np.ndarray = 0.0,
                 d_cutoff: float | np.ndarray = 1.0, reinit_after: int | None = None) -> None:
        if not rate > 0:
            raise ValueError(f"filter rate must be positive, got {rate}")
        self.rate = float(rate)
        self.min_cutoff = np.asarray(min_cutoff, dtype=np.float64)
        self.beta = np.asarray(beta, dtype=np.float64)
        self.d_cutoff = np.asarray(d_cutoff, dtype=np.float64)
        if np.any(self.min_cutoff <= 0) or np.any(self.d_cutoff <= 0) or np.any(self.beta < 0):
            raise ValueError("1€ filter needs min_cutoff > 0, d_cutoff > 0 and beta >= 0")
        self.reinit_after = None if reinit_after is None else int(reinit_after)
        self.reset()

    def reset(self) -> None:
        self._x: np.ndarray | None = None  # filtered value
        self._raw: np.ndarray | None = None  # last raw value (the paper's derivative uses it)
        self._dx: np.ndarray | None = None
        self._gap: np.ndarray | None = None
        self._seen: np.ndarray | None = None

    def latency_frames(self, speed: float | np.ndarray = 0.0) -> np.ndarray:
        """Lag in frames of the smoother at a given |speed| (units per second): tau / Te."""
        fc = self.min_cutoff + self.beta * np.abs(speed)
        return self.rate / (2.0 * np.pi * fc)

    def step(self, x: np.ndarray, valid: np.ndarray | None = None, period: float | None = None) -> np.ndarray:
        """Filter one sample per channel; ``period`` overrides 1/rate (e.g. from timestamps)."""
        x = np.asarray(x, dtype=np.float64)
        te = 1.0 / self.rate if period is None else float(period)
        ok = np.ones(x.shape, dtype=bool) if valid is None else np.broadcast_to(np.asarray(valid, bool), x.shape)
        if self._x is None:
            self._x = np.where(ok, x, 0.0)
            self._raw = self._x.copy()
            self._dx = np.zeros_like(self._x)
            self._seen = ok.copy()
            self._gap = np.zeros(x.shape, dtype=np.int64)
            return self._x.copy()
        stale = self._gap > self.reinit_after if self.reinit_after is not None else False
        fresh = ok & (~self._seen | stale)
        dx = (x - self._raw) / te
        a_d = smoothing_factor(self.d_cutoff, te)
        dx_hat = a_d * dx + (1.0 - a_d) * self._dx
        fc = self.min_cutoff + self.beta * np.abs(dx_hat)
        a = smoothing_factor(fc, te)
        x_hat = a * x + (1.0 - a) * self._x
        upd = ok & ~fresh
        self._x = np.where(upd, x_hat, np.where(fresh, x, self._x))
        self._dx = np.where(upd, dx_hat, np.where(fresh, 0.0, self._dx))
        self._raw = np.where(ok, x, self._raw)
        self._gap = np.where(ok, 0, self._gap + 1)
        self._seen |= ok
        return self._x.copy()

    def filter(self, X: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Run over a sequence (T, ...) from a fresh state; the same numbers as calling ``step``."""
        self.reset()
        X = np.asarray(X, dtype=np.float64)
        out = np.empty_like(X)
        for t in range(len(X)):
            out[t] = self.step(X[t], None if valid is None else valid[t])
        return out


def savgol_weights(lag: int, order: int = 2) -> np.ndarray:
    """Centre-point weights of a least-squares polynomial fit over 2 lag + 1 samples."""
    k = np.arange(-lag, lag + 1, dtype=np.float64)
    V = np.vander(k, order + 1, increasing=True)
    return np.linalg.pinv(V)[0]


class FixedLagSmoother:
    """Local polynomial fit over frames [t - 2 lag, t], evaluated at t - lag: latency ``lag`` frames.

    Missing samples are left out of each fit (weighted least squares), so a gap shorter than
    the window is bridged by the polynomial instead of a step.
    """

    def __init__(self, lag: int, order: int = 2) -> None:
        if lag < 1:
            raise ValueError("fixed-lag smoother needs lag >= 1 frame")
        self.lag = int(lag)
        self.order = min(int(order), 2 * self.lag)
        k = np.arange(-self.lag, self.lag + 1, dtype=np.float64)
        self._V = np.vander(k, self.order + 1, increasing=True)  # window x (order + 1)
        self.reset()

    @property
    def latency_frames(self) -> int:
        return self.lag

    def reset(self) -> None:
        self._buf: list[np.ndarray] = []
        self._ok: list[np.ndarray] = []
        self._last: np.ndarray | None = None

    def _centre(self, X: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Fit per channel: X, ok are (window, channels)."""
        w = ok.astype(np.float64)
        G = np.einsum("wc,wi,wj->cij", w, self._V, self._V) + 1e-9 * np.eye(self.order + 1)
        r = np.einsum("wc,wi,wc->ci", w, self._V, X)
        enough = w.sum(0) > self.order
        coef = np.linalg.solve(G, r[..., None])[..., 0]
        return np.where(enough, coef[:, 0], np.nan)

    def step(self, x: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Push frame t, return the estimate for frame t - lag (the first ``lag`` calls: earliest frame)."""
        x = np.asarray(x, dtype=np.float64)
        ok = np.ones(x.shape, bool) if valid is None else np.broadcast_to(np.asarray(valid, bool), x.shape)
        if not self._buf:  # pad the past with the first sample so the output starts at once
            self._buf = [x.copy()] * (2 * self.lag)
            self._ok = [ok.copy()] * (2 * self.lag)
        self._buf.append(x.copy())
        self._ok.append(ok.copy())
        del self._buf[: len(self._buf) - (2 * self.lag + 1)]
        del self._ok[: len(self._ok) - (2 * self.lag + 1)]
        X = np.stack(self._buf).reshape(len(self._buf), -1)
        M = np.stack(self._ok).reshape(len(self._ok), -1)
        est = self._centre(X, M)
        prev = X[self.lag] if self._last is None else self._last.reshape(-1)
        est = np.where(np.isnan(est), np.where(M[self.lag], X[self.lag], prev), est)
        self._last = est.reshape(x.shape)
        return self._last.copy()

    def filter(self, X: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Zero-phase over a whole sequence (T, ...): output t is the fit centred on t (edges shrink)."""
        X = np.asarray(X, dtype=np.float64)
        T = len(X)
        flat = X.reshape(T, -1)
        ok = np.ones(flat.shape, bool) if valid is None else np.broadcast_to(
            np.asarray(valid, bool).reshape(T, *X.shape[1:]), X.shape).reshape(T, -1)
        out = flat.copy()
        for t in range(T):
            a, b = max(0, t - self.lag), min(T, t + self.lag + 1)
            win = np.zeros((2 * self.lag + 1, flat.shape[1]))
            m = np.zeros(win.shape, bool)
            win[a - t + self.lag:b - t + self.lag] = flat[a:b]
            m[a - t + self.lag:b - t + self.lag] = ok[a:b]
            est = self._centre(win, m)
            out[t] = np.where(np.isnan(est), flat[t], est)
        return out.reshape(X.shape)


def endpoint_weights(window: int, order: int = 2) -> np.ndarray:
    """Weights over samples t - window + 1 .. t of a least-squares polynomial fit evaluated at t.

    The causal end of a Savitzky–Golay fit: exact (no lag, no bias) on polynomials of degree
    <= ``order``; ``sum(h**2)`` is the white-noise variance gain.
    """
    k = np.arange(-(window - 1), 1, dtype=np.float64)
    return np.linalg.pinv(np.vander(k, order + 1, increasing=True))[0]


class CausalPolyFilter:
    """Per channel, a least-squares polynomial through the last ``window`` samples, evaluated at the
    newest one: a causal smoother with no lag on motions up to degree ``order`` (a quadratic follows a
    constant acceleration), so noise is cut without the exponential smoother's delay.

    Missing samples are left out of the fit (weighted least squares); a channel with fewer than
    ``order + 1`` samples in the window passes its newest valid value through.
    """

    def __init__(self, window: int, order: int = 2) -> None:
        if window < order + 2:
            raise ValueError(f"causal polynomial filter needs window >= order + 2 ({order + 2}), got {window}")
        self.window = int(window)
        self.order = int(order)
        k = np.arange(-(self.window - 1), 1, dtype=np.float64)
        self._V = np.vander(k, self.order + 1, increasing=True)  # window x (order + 1)
        self._h = endpoint_weights(self.window, self.order)
        self.reset()

    @property
    def noise_gain(self) -> float:
        """Output / input variance of white noise (every sample valid)."""
        return float(np.sum(self._h**2))

    latency_frames = 0  # exact on polynomials of degree <= order

    def reset(self) -> None:
        self._ring: np.ndarray | None = None  # 2 window x channels: each sample written twice, so
        self._ring_ok: np.ndarray | None = None  # the last window is one contiguous slice (no roll)
        self._pos = 0
        self._last: np.ndarray | None = None
        self._full_run = 0  # consecutive frames with every channel valid

    def step(self, x: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        flat = x.reshape(-1)
        W = self.window
        if self._ring is not None and (valid is None or np.all(valid)):
            self._full_run += 1
            if self._full_run >= W:  # the whole window is valid: the fixed end-point weights
                p = self._pos
                self._ring[p] = self._ring[p + W] = flat
                self._ring_ok[p] = self._ring_ok[p + W] = True
                self._pos = (p + 1) % W
                out = self._h @ self._ring[p + 1:p + 1 + W]
                self._last = out.copy()
                return out.reshape(x.shape)
        else:
            self._full_run = 0
        ok = np.ones(x.shape, bool) if valid is None else np.broadcast_to(np.asarray(valid, bool), x.shape)
        okf = ok.reshape(-1)
        if self._ring is None:
            self._ring = np.zeros((2 * W, flat.size))
            self._ring_ok = np.zeros((2 * W, flat.size), bool)
            self._last = np.where(okf, flat, 0.0)
            self._full_run = int(okf.all())
        p = self._pos
        self._ring[p] = self._ring[p + W] = flat
        self._ring_ok[p] = self._ring_ok[p + W] = okf
        self._pos = (p + 1) % W
        from solvers.take_filter_kernels import causal_poly_frame  # numba only once a window is partly missing

        out = np.empty_like(flat)
        causal_poly_frame(self._ring, self._ring_ok, p + 1, self._h, self._V, flat, np.ascontiguousarray(okf),
                          self._last, out)
        return out.reshape(x.shape)

    def filter(self, X: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Run over a sequence (T, ...) from a fresh state; the same numbers as calling ``step``."""
        self.reset()
        X = np.asarray(X, dtype=np.float64)
        return np.stack([self.step(X[t], None if valid is None else valid[t]) for t in range(len(X))])


class FilteredSolver:
    """Any per-frame solver with optional filters on its input markers and on its output weights.

    ``marker_filter`` sees the (n x 3) displacements with the valid mask (a missing marker keeps
    its filter state; the inner solver still sees it as missing); ``weight_filter`` sees the
    inner solver's weights. Either is a ``OneEuroFilter``, a ``FixedLagSmoother`` or anything
    with ``step(x, valid)`` and ``reset()``. Weights are clipped back to the limits after
    filtering. ``latency_frames`` adds up the filters' fixed lags (the 1€ filter has none fixed).
    """

    def __init__(self, inner, marker_filter=None, weight_filter=None, lower: np.ndarray | None = None,
                 upper: np.ndarray | None = None) -> None:
        self.inner = inner
        self.marker_filter = marker_filter
        self.weight_filter = weight_filter
        self.lower = getattr(inner, "lower", None) if lower is None else np.asarray(lower, float)
        self.upper = getattr(inner, "upper", None) if upper is None else np.asarray(upper, float)

    @property
    def latency_frames(self) -> int:
        return sum(int(getattr(f, "latency_frames", 0)) for f in (self.marker_filter, self.weight_filter)
                   if f is not None and not callable(getattr(f, "latency_frames", None)))

    def reset(self) -> None:
        for part in (self.inner, self.marker_filter, self.weight_filter):
            if part is not None and hasattr(part, "reset"):
                part.reset()

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        valid = np.asarray(valid, dtype=bool)
        if self.marker_filter is not None:
            mask = None if valid.all() else np.broadcast_to(valid[:, None], np.shape(target))
            target = self.marker_filter.step(target, mask)
        w = self.inner.step(target, valid)
        if self.weight_filter is not None:
            w = self.weight_filter.step(w)
            if self.lower is not None:
                w = np.maximum(w, self.lower)
                np.minimum(w, self.upper, out=w)
        return w
