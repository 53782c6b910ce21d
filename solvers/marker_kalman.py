"""Constant-velocity Kalman filtering of marker coordinates, its noise chosen by the data's own likelihood.

Each coordinate of each stabilised marker is a white-noise-acceleration model (state: position and
velocity per frame; Bar-Shalom, Li & Kirubarajan 2001 §6.2.2), observed with noise variance ``r``.
Process noise ``q`` differs per marker (the mouth moves more than the forehead) and is chosen per
marker from a grid by the innovation log-likelihood of the take itself (prediction-error
decomposition, Harvey 1989 §3.4); ``r`` is shared. Offline: forward filter + Rauch-Tung-Striebel
smoother, with ``q`` chosen per marker *and frame* by the likelihood over a short centred window: one
``q`` for a whole take is a compromise that is too small for a blink's onset (issue 15: ICT blink peaks
0.63 of the truth's with one ``q``, 0.90 with the local choice) and too large while the face holds.
Streaming: a bank of filters selected per marker by exponentially discounted likelihood, with an
optional one-frame fixed-lag smoothing step. The bank runs over lambda = q / r only (21 filters), every
r's likelihood following from three sums per filter and marker (``StreamingMarkerKalman``): the same
filters as one per (r, q) on a q grid shifted by at most half a step, for a fifth of the work. The
shared r follows the take's noise, not the frame: it is re-chosen every frame for the first 60, then
every 8th (issue 15: the realeval rows are equal to every digit either way).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solvers import marker_kalman_kernels as kern


@dataclass(frozen=True)
class KalmanSettings:
    r_grid: tuple[float, ...] = tuple(np.round(np.array([0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0]) ** 2, 6))
    q_grid: tuple[float, ...] = tuple(np.logspace(-6, 1, 15))
    half_life_frames: float = 600.0  # streaming: likelihood memory
    max_gap_frames: int = 15  # offline: gaps up to this are bridged (interpolated by the smoother)
    # streaming: a marker unseen longer than this is reported missing, not extrapolated at constant velocity
    # (issue 15, ICT 0.2 mm: 15 frames -> 2 took weight RMSE 0.68 -> 0.45 x the oracle; 0, 1 and 2 alike)
    stream_max_gap_frames: int = 2
    local_frames: int = 4  # offline: q chosen per frame by the likelihood over +- this many frames
    # offline: the shared r chosen on at most this many markers, evenly spread (issue 39: on the ICT takes its
    # log-likelihood margin is > 1e4 and every eighth marker chose as all 60; the bank over all was ~1/4 of a solve)
    noise_markers: int = 12
    # offline: ... and on at most this many frames, the take's first (issue 39 item 2: on 24 ICT takes of six real
    # performances, 10 and 30 s at 0.5 and 0.2 mm, the first 600 chose as all, by > 600 log-likelihood units)
    noise_frames: int = 600


def _grid(s: KalmanSettings) -> tuple[np.ndarray, np.ndarray]:
    r, q = np.meshgrid(np.asarray(s.r_grid), np.asarray(s.q_grid), indexing="ij")
    return r.ravel(), q.ravel()


def _choose(loglik: np.ndarray, n_markers: int, n_r: int) -> tuple[int, np.ndarray]:
    """Shared r, per-marker q: K x 3n log-likelihoods -> (r index, per-marker filter index)."""
    per_marker = loglik.reshape(n_r, -1, n_markers, 3).sum(3)  # r x q x n
    best_q = per_marker.argmax(1)  # r x n
    total = np.take_along_axis(per_marker, best_q[:, None, :], 1)[:, 0].sum(1)
    ri = int(total.argmax())
    return ri, ri * per_marker.shape[1] + best_q[ri]


def smooth_take(targets: np.ndarray, valid: np.ndarray, settings: KalmanSettings | None = None,
                r: float | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """RTS-smoothed targets (T x n x 3), the validity after gap bridging, and the chosen noise.

    ``r`` (shared): as given (the ``"r"`` chosen on these markers before, e.g. by the pass before a rigid
    correction), else by the likelihood of ``settings.noise_markers`` markers over the take's first
    ``settings.noise_frames`` (one r is every marker's and every frame's: a dozen markers over ten seconds tell it
    as well as all); ``q`` per marker and frame by the likelihood of
    the fixed-``q`` filters' innovations over ``settings.local_frames`` either side (a local model
    choice, as an IMM's mode probabilities; Bar-Shalom et al. 2001 §11.6.6); then one filter with
    that time-varying ``q`` and the RTS pass."""
    from solvers.marker_smoother_kernels import bank_take, rts  # here: importing this module must not import numba

    s = settings or KalmanSettings()
    T, n, _ = targets.shape
    z = np.ascontiguousarray(targets, dtype=np.float64)
    seen = np.ascontiguousarray(valid, dtype=bool)
    none, no_best = np.zeros((0, 0, 0)), np.zeros((0, 0), np.int64)
    h = int(s.local_frames)
    if r is None:
        rk, qk = _grid(s)
        pick = _spread(n, s.noise_markers)
        k = len(pick)
        ll = np.zeros((len(rk), k, 3))
        span = slice(0, max(1, s.noise_frames))
        bank_take(np.ascontiguousarray(z[span, pick]), np.ascontiguousarray(seen[span, pick]),
                  np.repeat(rk[:, None], k, 1), np.repeat(qk[None, :, None], k, 2), 1e2, ll, h, no_best, none, none,
                  none, none)
        r = s.r_grid[_choose(ll, k, len(s.r_grid))[0]]
    qg, r0 = np.asarray(s.q_grid, float), float(r)
    best = np.empty((T, n), np.int64)  # per frame and marker: the q of the best likelihood over +- h frames
    bank_take(z, seen, np.full((len(qg), n), r0), np.repeat(qg[None, :, None], n, 2), 1e2, none, h, best, none, none,
              none, none)
    qt = qg[best]  # T x n
    xs, xp = np.zeros((T, 2, 3 * n)), np.zeros((T, 2, 3 * n))
    ps, pp = np.zeros((T, 3, n)), np.zeros((T, 3, n))
    bank_take(z, seen, np.full((1, n), r0), np.ascontiguousarray(qt[:, None, :]), 1e2, none, h, no_best, xs, ps, xp,
              pp)
    out = np.empty((T, 3 * n))
    rts(xs, ps, xp, pp, out)
    return out.reshape(T, n, 3), bridged(valid, s.max_gap_frames), {
        "noise_mm": float(np.sqrt(r0)), "r": r0, "q_per_marker": np.median(qt, axis=0)}


def _spread(n: int, k: int) -> np.ndarray:
    """At most ``k`` indices evenly spread over ``range(n)``."""
    return np.unique(np.linspace(0, n - 1, min(n, max(1, k))).astype(int))


def _rts(xs: np.ndarray, ps: np.ndarray, xp: np.ndarray, pp: np.ndarray) -> np.ndarray:
    """Rauch-Tung-Striebel backward pass over filtered (xs, ps) and predicted (xp, pp) 2-states (the numpy
    reference of the compiled ``solvers.marker_smoother_kernels.rts``)."""
    T = len(xs)
    x, v = xs[-1, 0].copy(), xs[-1, 1].copy()
    out = np.empty((T, xs.shape[2]))
    out[-1] = x
    for t in range(T - 2, -1, -1):
        f00, f01, f11 = ps[t]
        a00, a01, a11 = pp[t + 1]
        det = a00 * a11 - a01 * a01
        i00, i01, i11 = a11 / det, -a01 / det, a00 / det
        # J = Pf F^T Pp^-1, F^T = [[1, 0], [1, 1]]
        b00, b01, b10, b11 = f00 + f01, f01, f01 + f11, f11
        j00, j01 = b00 * i00 + b01 * i01, b00 * i01 + b01 * i11
        j10, j11 = b10 * i00 + b11 * i01, b10 * i01 + b11 * i11
        dx, dv = x - xp[t + 1, 0], v - xp[t + 1, 1]
        x = xs[t, 0] + j00 * dx + j01 * dv
        v = xs[t, 1] + j10 * dx + j11 * dv
        out[t] = x
    return out


def bridged(valid: np.ndarray, max_gap: int) -> np.ndarray:
    """Valid, plus interior gaps of at most ``max_gap`` frames (the smoother bridges them)."""
    v = np.asarray(valid, bool)
    T = len(v)
    frame = np.arange(T)[:, None]
    last = np.maximum.accumulate(np.where(v, frame, -1), axis=0)  # the last frame seen at or before
    following = np.minimum.accumulate(np.where(v, frame, T)[::-1], axis=0)[::-1]  # the next at or after
    return v | ((last >= 0) & (following < T) & (following - last - 1 <= max_gap))


R_SETTLE_FRAMES, R_EVERY = 60, 8  # streaming: the shared r re-chosen every frame at first, then every 8th


class StreamingMarkerKalman:
    """Per-frame marker filter: each marker follows the (r, q) with the best discounted likelihood
    (r shared). ``lag`` 1 returns frame t - 1 smoothed with frame t.

    A constant-velocity filter's gains depend on ``q`` and ``r`` only through lambda = q / r: its
    covariances are r times those of the filter (1, lambda), so every r shares that filter's
    innovations e and their unit variances s, and the log-likelihood of (r, lambda) over the
    coordinates and frames is -(c log r + sum log s + sum e^2 / (s r)) / 2 from three discounted
    sums per (lambda, marker). One bank over a lambda grid (the q grid's spacing, spanning every
    q / r the grids allow) serves every r: 21 filters instead of 7 x 15 (Bar-Shalom et al. 2001
    §6.2.2 for the filter; the steady state's dependence on q / r alone is their §6.2.3 tracking
    index). Each r may choose the lambdas whose q = lambda r lies in the q grid's range. A frame is
    one compiled call (solvers.marker_kalman_kernels.frame)."""

    def __init__(self, n_markers: int, settings: KalmanSettings | None = None, lag: int = 1) -> None:
        self.s = settings or KalmanSettings()
        self.n, self.lag = n_markers, lag
        r, q = np.asarray(self.s.r_grid, float), np.asarray(self.s.q_grid, float)
        step = np.log(q[1] / q[0]) if len(q) > 1 else 1.0
        span = np.log(q.max() / r.min()) - np.log(q.min() / r.max())
        self.lam = q.min() / r.max() * np.exp(step * np.arange(int(np.ceil(span / step - 1e-9)) + 1))
        q_of = self.lam[None, :] * r[:, None]  # r x lambda
        half = np.exp(0.5 * step)
        allowed = (q_of >= q.min() / half) & (q_of <= q.max() * half)
        self.excluded = np.where(allowed, 0.0, np.inf)[:, None, :]  # r x 1 x lambda
        self._excluded = np.ascontiguousarray(self.excluded[:, 0])
        self.log_r, self.inv_r = np.log(r), 1.0 / r
        self._noise_of = [float(np.sqrt(v)) for v in self.s.r_grid]  # noise_mm per r
        self.p11_start = 1e2 / float(np.median(r))  # 1e2 mm^2/frame^2 at the middle r
        self.decay = 0.5 ** (1.0 / self.s.half_life_frames)
        self.reset()

    def reset(self) -> None:
        K, n = len(self.lam), self.n
        self._xv = np.zeros((2, 2, K, 3, n))  # (buffer, position / velocity, filter, coordinate, marker)
        self._p = np.empty((2, 3, K, n))  # (buffer, p00 / p01 / p11, filter, marker)
        self._p[:, kern.P00], self._p[:, kern.P01], self._p[:, kern.P11] = 1e6, 0.0, self.p11_start
        self._cur = 0
        self.started = np.zeros(n, dtype=bool)
        self.count = np.zeros(n)  # discounted updated coordinates
        self.log_s = np.zeros((K, n))  # discounted sum of log s over coordinates
        self.energy = np.zeros((K, n))  # discounted sum of e^2 / s
        self._slog = np.full((2, K, n), np.nan)  # each filter's last s and its log
        self.unseen = np.zeros(n, dtype=np.int64)
        self.sightings = np.zeros(n, dtype=np.int64)
        self._pick = np.zeros(n, dtype=np.int64)
        self.prev: np.ndarray | None = None
        self.t = 0
        self._ri = len(self.s.r_grid) // 2
        self.noise_mm = float(np.sqrt(np.median(self.s.r_grid)))  # the shared r chosen so far

    def step(self, target: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Filtered (lag 0) or one-frame-smoothed (lag 1) markers n x 3 and their validity."""
        valid = np.ascontiguousarray(valid, bool)
        z = np.ascontiguousarray(target, float).reshape(self.n, 3)
        every_r = self.t < R_SETTLE_FRAMES or self.t % R_EVERY == 0  # the shared r follows the take, not the frame
        smooth = self.lag != 0 and self.t > 0
        out, ok = np.empty((self.n, 3)), np.empty(self.n, bool)
        self._ri = kern.frame(self._xv, self._p, self._cur, self.lam, self.p11_start, self.started, self.sightings,
                              self.unseen, self.count, self.log_s, self.energy, self._slog, z, valid, self.t > 0,
                              self.decay, self.inv_r, self.log_r, self._excluded, self._ri, every_r, self._pick, smooth,
                              self.s.stream_max_gap_frames, out, ok)
        self._cur = 1 - self._cur
        self.noise_mm = self._noise_of[self._ri]
        self.t += 1
        if not smooth:
            return out, ok
        prev_ok = self.prev if self.prev is not None else ok
        self.prev = ok
        return out, prev_ok
