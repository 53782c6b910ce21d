"""The whole-array numpy streaming marker filter (solvers/marker_kalman.py before its frame step was compiled):
the reference that ``solvers.marker_kalman_kernels`` is tested against (tests/test_marker_kalman.py)."""

from __future__ import annotations

import numpy as np

from solvers.marker_kalman import R_EVERY, R_SETTLE_FRAMES, KalmanSettings, _Bank


class NumpyStreamingMarkerKalman:
    """Per-frame marker filter: each marker follows the (r, q) with the best discounted likelihood
    (r shared). ``lag`` 1 returns frame t - 1 smoothed with frame t.

    A constant-velocity filter's gains depend on ``q`` and ``r`` only through lambda = q / r: its
    covariances are r times those of the filter (1, lambda), so every r shares that filter's
    innovations e and their unit variances s, and the log-likelihood of (r, lambda) over the
    coordinates and frames is -(c log r + sum log s + sum e^2 / (s r)) / 2 from three discounted
    sums per (lambda, marker). One bank over a lambda grid (the q grid's spacing, spanning every
    q / r the grids allow) serves every r: 21 filters instead of 7 x 15 (Bar-Shalom et al. 2001
    §6.2.2 for the filter; the steady state's dependence on q / r alone is their §6.2.3 tracking
    index). Each r may choose the lambdas whose q = lambda r lies in the q grid's range."""

    def __init__(self, n_markers: int, settings: KalmanSettings | None = None, lag: int = 1) -> None:
        self.s = settings or KalmanSettings()
        self.n, self.lag = n_markers, lag
        self._idx = np.arange(n_markers)
        r, q = np.asarray(self.s.r_grid, float), np.asarray(self.s.q_grid, float)
        step = np.log(q[1] / q[0]) if len(q) > 1 else 1.0
        span = np.log(q.max() / r.min()) - np.log(q.min() / r.max())
        self.lam = q.min() / r.max() * np.exp(step * np.arange(int(np.ceil(span / step - 1e-9)) + 1))
        q_of = self.lam[None, :] * r[:, None]  # r x lambda
        half = np.exp(0.5 * step)
        allowed = (q_of >= q.min() / half) & (q_of <= q.max() * half)
        self.excluded = np.where(allowed, 0.0, np.inf)[:, None, :]  # r x 1 x lambda
        self.log_r, self.inv_r = np.log(r)[:, None], (1.0 / r)[:, None, None]
        self.p11_start = 1e2 / float(np.median(r))  # _Bank's 1e2 mm^2/frame^2 at the middle r
        self.reset()

    def reset(self) -> None:
        self.bank = _Bank(np.ones(len(self.lam)), self.lam, self.n, p11_start=self.p11_start)
        self.count = np.zeros(self.n)  # discounted updated coordinates
        self.log_s = np.zeros((self.n, len(self.lam)))  # discounted sum of log s over coordinates
        self.energy = np.zeros((self.n, len(self.lam)))  # discounted sum of e^2 / s
        self.decay = 0.5 ** (1.0 / self.s.half_life_frames)
        self.unseen = np.zeros(self.n, dtype=int)
        self.sightings = np.zeros(self.n, dtype=int)
        self.prev: tuple | None = None
        self.t = 0
        self._ri = len(self.s.r_grid) // 2
        self.noise_mm = float(np.sqrt(np.median(self.s.r_grid)))  # the shared r chosen so far

    def _cost(self, ri: int | slice = slice(None)) -> np.ndarray:
        """-2 log-likelihood less c log r per (r, marker, lambda), for the r at ``ri`` (all by
        default): sum log s + sum e^2 / s / r, infinite for the lambdas that r may not choose."""
        cost = self.energy * self.inv_r[ri]  # marker x lambda per r: reductions over the contiguous axis
        cost += self.log_s
        cost += self.excluded[ri]
        return cost

    def choose(self) -> tuple[int, np.ndarray]:
        """(r index, lambda index per marker) of the best discounted likelihood: the cost minimised over
        the lambdas per (r, marker) (c log r does not depend on lambda), c log r added, summed over the
        markers per r."""
        cost = self._cost()
        total = (cost.min(2) + self.log_r * self.count).sum(1)
        ri = int(total.argmin())
        return ri, cost[ri].argmin(1)

    def step(self, target: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Filtered (lag 0) or one-frame-smoothed (lag 1) markers n x 3 and their validity."""
        valid = np.asarray(valid, bool)
        b = self.bank
        if self.t:  # by reference: predict and update make new arrays
            before = (b.x, b.v, b.p00, b.p01, b.p11)
            b.predict()
            pred = (b.x, b.v, b.p00, b.p01, b.p11)
        e, s, upd = b.correct(np.asarray(target, float).reshape(self.n, 3), valid)
        use = upd & (self.sightings >= 2)  # the second sighting's innovation is the diffuse velocity's
        self.sightings += valid
        d = self.decay
        self.count = d * self.count + 3.0 * use
        self.log_s *= d
        self.energy *= d
        if use.all():
            self.log_s += 3.0 * np.log(s).T
            self.energy += (np.einsum("knc,knc->kn", e, e) / s).T
        else:
            self.log_s += np.where(use, 3.0 * np.log(s), 0.0).T
            self.energy += np.where(use, np.einsum("knc,knc->kn", e, e) / s, 0.0).T
        self.unseen = np.where(valid, 0, self.unseen + 1)
        if self.t < R_SETTLE_FRAMES or self.t % R_EVERY == 0:
            self._ri, pick = self.choose()
        else:  # the shared r changes on the take's noise, not from frame to frame
            pick = self._cost(self._ri).argmin(1)
        self.noise_mm = float(np.sqrt(self.s.r_grid[self._ri]))
        flat = pick * self.n + self._idx  # each marker's chosen filter in the K x n arrays, flattened
        ok = b.started & (self.unseen <= self.s.stream_max_gap_frames)
        if self.lag == 0 or not self.t:
            self.t += 1
            return b.x.reshape(-1, 3)[flat], ok
        self.t += 1
        fx, fv, px, pv, x, v = (a.reshape(-1, 3)[flat] for a in (before[0], before[1], pred[0], pred[1], b.x, b.v))
        f00, f01, a00, a01, a11 = (a.ravel()[flat] for a in (before[2], before[3], pred[2], pred[3], pred[4]))
        det = a00 * a11 - a01 * a01
        j00 = (((f00 + f01) * a11 - f01 * a01) / det)[:, None]
        j01 = ((-(f00 + f01) * a01 + f01 * a00) / det)[:, None]
        x = fx + j00 * (x - px) + j01 * (v - pv)
        prev_ok = self.prev if self.prev is not None else ok
        self.prev = ok
        return x, prev_ok
