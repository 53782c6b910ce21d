"""The whole-array numpy marker filters (solvers/marker_kalman.py before they were compiled): the streaming bank,
the reference ``solvers.marker_kalman_kernels`` is tested against, and the offline smoother's passes, the reference
of ``solvers.marker_smoother_kernels`` (tests/test_marker_kalman.py)."""

from __future__ import annotations

import numpy as np

from solvers.marker_kalman import (
    R_EVERY,
    R_SETTLE_FRAMES,
    KalmanSettings,
    StreamingMarkerKalman,
    _choose,
    _grid,
    _rts,
    _spread,
    bridged,
)


class NumpyStreamingMarkerKalman(StreamingMarkerKalman):
    """The streaming filter (the method: ``StreamingMarkerKalman``) as whole-array numpy calls on a ``_Bank``."""

    def __init__(self, n_markers: int, settings: KalmanSettings | None = None, lag: int = 1) -> None:
        super().__init__(n_markers, settings, lag)
        self._idx = np.arange(n_markers)
        self.log_r, self.inv_r = self.log_r[:, None], self.inv_r[:, None, None]

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


class _Bank:
    """K filters (rows) over n markers' 3 coordinates, vectorised; ``r``, ``q`` per row (K,) or per
    row and marker (K, n). A marker's three coordinates share their visibility and noise, so their
    covariances are equal: kept once per marker (K x n), the states per coordinate (K x n x 3)."""

    def __init__(self, r: np.ndarray, q: np.ndarray, n: int, p11_start: float = 1e2) -> None:
        self.r, self.q = (r, q) if np.ndim(r) == 2 else (r[:, None], q[:, None])
        k = len(self.r)
        self.p11_start = p11_start  # velocity variance at a marker's first sighting
        self.x = np.zeros((k, n, 3))
        self.v = np.zeros((k, n, 3))
        self.p00 = np.full((k, n), 1e6)
        self.p01 = np.zeros((k, n))
        self.p11 = np.full((k, n), p11_start)
        self.started = np.zeros(n, dtype=bool)

    def predict(self) -> None:
        """New arrays, never in place: callers keep the previous state by reference."""
        self.x = self.x + self.v
        p00 = self.p00 + 2 * self.p01 + self.p11 + self.q / 3
        p01 = self.p01 + self.p11 + self.q / 2
        self.p00, self.p01, self.p11 = p00, p01, self.p11 + self.q

    def update(self, z: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """Update with ``z`` (n x 3) where ``seen`` (n,); returns the innovation log-likelihood
        (K x n x 3, 0 where unseen)."""
        e, s, upd = self.correct(z, seen)
        return np.where(upd[:, None], -0.5 * (np.log(s)[..., None] + e * e / s[..., None]), 0.0)

    def correct(self, z: np.ndarray, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The update without the likelihood: innovations (K x n x 3, 0 where not updated), their
        variances (K x n) and which markers were updated (n,; not at their first sighting)."""
        first = seen & ~self.started
        if first.any():  # start at the first sighting, velocity unknown (on copies: see predict)
            self.x, self.v = self.x.copy(), self.v.copy()
            self.p00, self.p01, self.p11 = self.p00.copy(), self.p01.copy(), self.p11.copy()
            self.x[:, first] = z[first]
            self.v[:, first] = 0.0
            self.p00[:, first] = np.broadcast_to(self.r, self.p00.shape)[:, first]
            self.p01[:, first] = 0.0
            self.p11[:, first] = self.p11_start
            self.started |= first
        upd = seen & ~first
        s = self.p00 + self.r
        k0, k1 = self.p00 / s, self.p01 / s
        if upd.all():
            e = z - self.x
        else:
            e = np.where(upd[:, None], z - self.x, 0.0)
            k0, k1 = np.where(upd, k0, 0.0), np.where(upd, k1, 0.0)
        self.x = self.x + k0[..., None] * e
        self.v = self.v + k1[..., None] * e
        p01 = self.p01
        self.p00 = self.p00 - k0 * self.p00
        self.p01 = p01 - k0 * p01
        self.p11 = self.p11 - k1 * p01
        return e, s, upd


def numpy_smooth_take(targets: np.ndarray, valid: np.ndarray, settings: KalmanSettings | None = None
                ) -> tuple[np.ndarray, np.ndarray, dict]:
    """``smooth_take`` (the method is described there) as numpy passes over a ``_Bank``."""
    s = settings or KalmanSettings()
    T, n, _ = targets.shape
    z = np.asarray(targets, float)
    seen = np.asarray(valid, bool)
    r, q = _grid(s)
    pick = _spread(n, s.noise_markers)
    bank = _Bank(r, q, len(pick))
    ll = np.zeros((len(r), len(pick), 3))
    for t in range(T):
        if t:
            bank.predict()
        ll += bank.update(z[t, pick], seen[t, pick])
    ri, _ = _choose(ll, len(pick), len(s.r_grid))
    qg, r0 = np.asarray(s.q_grid, float), float(s.r_grid[ri])
    bank = _Bank(np.full(len(qg), r0), qg, n)
    cum = np.zeros((T + 1, len(qg), n))
    for t in range(T):
        if t:
            bank.predict()
        cum[t + 1] = cum[t] + bank.update(z[t], seen[t]).sum(2)
    h = int(s.local_frames)
    frames = np.arange(T)
    local = cum[np.minimum(frames + h + 1, T)] - cum[np.maximum(frames - h, 0)]  # T x q x n
    qt = qg[local.argmax(1)]  # T x n
    chosen = _Bank(np.full((1, n), r0), qt[:1].copy(), n)
    xs, ps, xp, pp = [], [], [], []
    for t in range(T):
        if t:
            chosen.q = qt[t][None]
            chosen.predict()
        xp.append(np.stack([chosen.x[0].ravel(), chosen.v[0].ravel()]))
        pp.append(np.stack([chosen.p00[0], chosen.p01[0], chosen.p11[0]]))
        chosen.update(z[t], seen[t])
        xs.append(np.stack([chosen.x[0].ravel(), chosen.v[0].ravel()]))
        ps.append(np.stack([chosen.p00[0], chosen.p01[0], chosen.p11[0]]))
    per_coordinate = [np.repeat(np.array(a), 3, axis=2) for a in (ps, pp)]
    out = _rts(np.array(xs), per_coordinate[0], np.array(xp), per_coordinate[1])
    return out.reshape(T, n, 3), bridged(valid, s.max_gap_frames), {
        "noise_mm": float(np.sqrt(r0)), "q_per_marker": np.median(qt, axis=0)}
