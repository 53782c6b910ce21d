"""Motion-model (tracking) filters for weight channels: a constant-velocity Kalman filter and an
interacting multiple model (IMM) of a 'hold' and a 'move' constant-velocity model.

Why: the first-order 1€ filter (``solvers.filters.OneEuroFilter``) lags on every ramp; a filter
whose state carries a velocity has zero steady-state lag on a ramp. Per channel the state is
``[x, v]`` (value, velocity per frame), ``F = [[1, 1], [0, 1]]``, the measurement ``y = x + n``
with ``n ~ N(0, R)``, and the discrete white-noise acceleration model (DWNA; Bar-Shalom, Li &
Kirubarajan, "Estimation with Applications to Tracking and Navigation", Wiley 2001, §6.3.2):
``Q = q G G^T``, ``G = [1/2, 1]``, ``q`` the variance of the per-frame velocity change
(acceleration sd x period^2, squared). Its steady state is the alpha-beta filter with the
tracking index ``Lambda = sqrt(q) / sqrt(R)`` (Kalata 1984; Bar-Shalom et al. §6.5.3):
``alpha_beta_gains``.

A single CV model is a fixed compromise: small ``q`` smooths but lags on an onset (a blink starts
with a large acceleration), large ``q`` follows but passes noise. The IMM (Blom & Bar-Shalom
1988; Bar-Shalom et al. 2001 §11.6.6) runs both models, mixes their states by the Markov mode
probabilities and weights their outputs by the innovation likelihoods, so a channel is smoothed
hard while its innovations look like noise and follows at once when they do not (the classic
maneuvering-target answer). Vectorised over channels; ``R`` per channel (for weights from a fit:
the noise variance of each weight, e.g. ``sigma^2 / |b_k|^2``).
"""

from __future__ import annotations

import numpy as np


def dwna_variance(accel_sd: float | np.ndarray, rate: float) -> np.ndarray:
    """DWNA process-noise intensity per frame: ``(a T^2)^2`` for acceleration sd ``a`` (units/s^2)."""
    return (np.asarray(accel_sd, dtype=np.float64) / float(rate) ** 2) ** 2


def alpha_beta_gains(q: float | np.ndarray, r: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Steady-state gains of the DWNA constant-velocity Kalman filter (Kalata 1984; Bar-Shalom et al.
    2001 eq. 6.5.3-16/17): ``Lambda = sqrt(q / r)``,
    ``alpha = -(L^2 + 8L - (L + 4) sqrt(L^2 + 8L)) / 8``, ``beta = (L^2 + 4L - L sqrt(L^2 + 8L)) / 4``."""
    lam = np.sqrt(np.asarray(q, dtype=np.float64) / np.asarray(r, dtype=np.float64))
    root = np.sqrt(lam * lam + 8.0 * lam)
    alpha = -(lam * lam + 8.0 * lam - (lam + 4.0) * root) / 8.0
    beta = (lam * lam + 4.0 * lam - lam * root) / 4.0
    return alpha, beta


class _CV:
    """State of one constant-velocity model over m channels: mean x, v and covariance P (3 terms)."""

    def __init__(self, y: np.ndarray, r: np.ndarray, v_var: np.ndarray) -> None:
        self.x, self.v = y.copy(), np.zeros_like(y)
        self.p00, self.p01, self.p11 = r.copy(), np.zeros_like(y), v_var.copy()

    def predict(self, q: np.ndarray) -> None:
        self.x = self.x + self.v
        self.p00, self.p01, self.p11 = (self.p00 + 2 * self.p01 + self.p11 + q / 4,
                                        self.p01 + self.p11 + q / 2, self.p11 + q)

    def update(self, y: np.ndarray, r: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Measurement update where ``ok``; returns innovation and its variance (for the likelihood)."""
        s = self.p00 + r
        e, k0, k1 = y - self.x, self.p00 / s, self.p01 / s
        if not ok.all():
            e, k0, k1 = np.where(ok, e, 0.0), k0 * ok, k1 * ok
        self.x, self.v = self.x + k0 * e, self.v + k1 * e
        self.gain = (k0, k1)
        self.p00, self.p01, self.p11 = (1 - k0) * self.p00, (1 - k0) * self.p01, self.p11 - k1 * self.p01
        return e, s


class KalmanCV:
    """Constant-velocity Kalman filter per channel (DWNA process noise ``q``, measurement variance ``r``).

    ``step(y, valid)``: a missing sample is predicted through (no update). The first sample
    initialises the value (variance ``r``) with zero velocity (variance ``v_var``, default: ``r``).
    """

    def __init__(self, q: float | np.ndarray, r: float | np.ndarray, v_var: float | np.ndarray | None = None) -> None:
        self.q = np.asarray(q, dtype=np.float64)
        self.r = np.asarray(r, dtype=np.float64)
        self.v_var = self.r if v_var is None else np.asarray(v_var, dtype=np.float64)
        if np.any(self.r <= 0) or np.any(self.q < 0):
            raise ValueError("Kalman filter needs r > 0 and q >= 0")
        self.reset()

    latency_frames = 0  # no steady-state lag on a ramp (constant-velocity model)

    def reset(self) -> None:
        self._m: _CV | None = None

    @property
    def gain(self) -> tuple[np.ndarray, np.ndarray]:
        """The last update's Kalman gains (alpha, beta in the steady state)."""
        return self._m.gain

    def step(self, y: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        y = np.asarray(y, dtype=np.float64)
        ok = np.ones(y.shape, bool) if valid is None else np.broadcast_to(np.asarray(valid, bool), y.shape)
        r, q = np.broadcast_to(self.r, y.shape), np.broadcast_to(self.q, y.shape)
        if self._m is None:
            self._m = _CV(np.where(ok, y, 0.0), r, np.broadcast_to(self.v_var, y.shape))
            return self._m.x.copy()
        self._m.predict(q)
        self._m.update(y, r, ok)
        return self._m.x.copy()

    def filter(self, Y: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Run over a sequence (T, ...) from a fresh state; the same numbers as calling ``step``."""
        self.reset()
        return np.stack([self.step(y, None if valid is None else valid[t]) for t, y in enumerate(np.asarray(Y))])


class IMMFilter:
    """IMM of two constant-velocity models per channel: 'hold' (process noise ``q_hold``) and 'move'
    (``q_move``), Markov switching with mean sojourn ``sojourn_frames`` in either mode
    (Bar-Shalom et al. 2001 §11.6.6: interaction/mixing, mode-matched filtering, mode probability
    update, combination). The output is the probability-weighted mean of the two models' values.

    The step runs in a compiled kernel (``solvers.imm_kernels``, imported on the first sample so that a
    process that never filters does not load numba): one loop over channels, ~5 µs at 150 channels where
    ~40 whole-array numpy calls took ~28 µs (docs/performance.md, "Compiled kernels (numba)").
    A missing sample (``valid`` False, possibly NaN) is predicted through: no update, likelihood 1.
    """

    def __init__(self, q_hold: float | np.ndarray, q_move: float | np.ndarray, r: float | np.ndarray,
                 sojourn_frames: float = 100.0, p_move: float = 0.1) -> None:
        self.q = (np.asarray(q_hold, dtype=np.float64), np.asarray(q_move, dtype=np.float64))
        self.r = np.asarray(r, dtype=np.float64)
        if np.any(self.r <= 0) or np.any(self.q[0] < 0) or np.any(self.q[1] < 0):
            raise ValueError("IMM filter needs r > 0 and q >= 0")
        if not sojourn_frames > 1:
            raise ValueError(f"IMM mean sojourn must exceed one frame, got {sojourn_frames}")
        stay = 1.0 - 1.0 / float(sojourn_frames)
        self.transition = np.array([[stay, 1 - stay], [1 - stay, stay]])  # [from, to]
        self.p_move = float(p_move)
        self.reset()

    latency_frames = 0  # both models are constant-velocity: no steady-state lag on a ramp

    def reset(self) -> None:
        self._shape: tuple | None = None
        self._state: np.ndarray | None = None  # (imm_kernels.N_STATE, channels)

    @property
    def move_probability(self) -> np.ndarray | None:
        """Each channel's current probability of the 'move' model (diagnostics)."""
        if self._state is None:
            return None
        from solvers import imm_kernels

        return self._state[imm_kernels.MU_MOVE].reshape(self._shape)

    def _start(self, y: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Both models at the first sample (variance r, velocity 0 with variance r)."""
        from solvers import imm_kernels as k

        self._kernels = k
        self._shape = y.shape
        C = y.size
        start = np.where(ok, y, 0.0).reshape(C)
        st = np.zeros((k.N_STATE, C))
        st[k.XH] = st[k.XM] = start
        st[k.R] = st[k.P00H] = st[k.P00M] = st[k.P11H] = st[k.P11M] = np.broadcast_to(self.r, y.shape).reshape(C)
        st[k.Q_HOLD] = np.broadcast_to(self.q[0], y.shape).reshape(C)
        st[k.Q_MOVE] = np.broadcast_to(self.q[1], y.shape).reshape(C)
        st[k.MU_HOLD], st[k.MU_MOVE] = 1 - self.p_move, self.p_move
        self._state = st
        self._all = np.ones(C, bool)
        return start.reshape(y.shape).copy()

    def set_noise(self, r: float | np.ndarray) -> None:
        """A new measurement variance from the next sample on, the models' state kept (a streaming fit whose
        noise per channel changes with its regularisation)."""
        self.r = np.asarray(r, dtype=np.float64)
        if self._state is not None:
            self._state[self._kernels.R] = np.broadcast_to(self.r, self._shape).reshape(-1)

    def share_move(self, share: float, out: np.ndarray) -> None:
        """After a step: each channel's 'move' probability raised to at least ``share`` x the largest, ``out`` (that
        step's output) recombined with it (solvers.imm_kernels.share_move)."""
        self._kernels.share_move(self._state, float(share), out.reshape(-1))

    def step(self, y: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        y = np.asarray(y, dtype=np.float64)
        ok = None if valid is None else np.require(np.broadcast_to(valid, y.shape), bool, "CW").reshape(-1)
        if self._state is None:
            return self._start(y, np.ones(y.shape, bool) if ok is None else ok.reshape(y.shape))
        if y.size != self._state.shape[1]:  # the compiled step indexes the state by channel, unchecked
            raise ValueError(f"IMM filter tracks {self._state.shape[1]} channels, got a sample of {y.size}")
        out = np.empty(y.shape)
        self._kernels.imm_step(self._state, y.reshape(-1), self._all if ok is None else ok, self.transition,
                               out.reshape(-1))
        return out

    def filter(self, Y: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Run over a sequence (T, ...) from a fresh state; the same numbers as calling ``step``."""
        self.reset()
        Y = np.asarray(Y, dtype=np.float64)
        if not len(Y):
            return Y.copy()
        out = np.empty(Y.shape)
        ok = None if valid is None else np.broadcast_to(np.asarray(valid, bool), Y.shape)
        out[0] = self.step(Y[0], None if ok is None else ok[0])
        T, C = len(Y), out[0].size
        ok = np.ones((T - 1, C), bool) if ok is None else np.require(ok[1:], bool, "CW").reshape(T - 1, C)
        # contiguous, writable arrays: one compiled signature for every caller (a reversed or read-only
        # view would compile another)
        self._kernels.imm_take(self._state, np.require(Y[1:], np.float64, "CW").reshape(T - 1, C), ok,
                               self.transition, out[1:].reshape(T - 1, C))
        return out


def variances_along(axes: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """A covariance (m x m) as variances along orthonormal ``axes`` (its diagonal in them; the rest dropped)."""
    return np.maximum(((np.asarray(cov, dtype=np.float64) @ axes) * axes).sum(0), 1e-300)


class NoiseShrink:
    """Per direction, the IMM's output pulled toward the direction's running mean by the Wiener gain
    ``g = 1 - c n / v`` (clipped to [0, 1]): ``v`` the direction's running variance, ``n`` its frame-to-frame
    noise variance, the mean of ``(u_t - u_{t-1})^2 / 2`` over the frames it holds (white noise: that is its
    variance). The posterior mean of a stationary Gaussian signal in white noise, with both variances read from
    the stream itself (empirical Bayes).

    Why: along the fit's ill-seen directions its error is slow (the bounds and the marker filter shape it), so the
    IMM's hold model keeps it as signal, and the fit's nominal variance (noise^2 V' C V) overstates the fit's
    actual error there 7-80 x, so it cannot tell (issue 41, ICT 0.2 mm: 72 % of the streamed weight MSE lay in the
    quarter of the directions with the largest nominal variance). While any direction moves (the largest
    'move' probability; ``near``: of the directions that move its markers, ``shared_markers``) the pull is let go, so
    a blink that the fit spreads over a noisy direction keeps its peak.
    Nothing is pulled over the first ``warm_frames`` (the spread is not known yet)."""

    def __init__(self, c: float = 4.0, warm_frames: int = 60, half_life_frames: float = 3600.0) -> None:
        if not c > 0 or warm_frames < 2 or not half_life_frames > 0:
            raise ValueError("NoiseShrink needs c > 0, warm_frames >= 2 and half_life_frames > 0")
        self.c, self.warm = float(c), int(warm_frames)
        self.floor = 1.0 - 0.5 ** (1.0 / float(half_life_frames))  # the smallest averaging weight: a long memory
        self.reset()

    def reset(self) -> None:
        self.n = 0
        self._state: np.ndarray | None = None  # (imm_kernels.N_SHRINK, directions)

    @property
    def mean(self) -> np.ndarray | None:
        """Each direction's running mean (what it is pulled toward)."""
        return None if self._state is None else self._state[self._kernels.S_MEAN].copy()

    def step(self, u: np.ndarray, move_before: np.ndarray, x: np.ndarray, move_after: np.ndarray,
             near: np.ndarray | None = None) -> np.ndarray:
        """Sample ``u`` (the fit along the directions) and the IMM's output ``x`` for it -> the output pulled;
        ``move_before`` / ``move_after``: the IMM's 'move' probabilities before and after its step. One compiled
        call (solvers.imm_kernels): as a dozen numpy calls it cost ~27 us a frame at 53 directions."""
        if self._state is None:
            from solvers import imm_kernels

            self._kernels = imm_kernels
            self._state = np.zeros((imm_kernels.N_SHRINK, u.size))
        out = np.empty(u.size)
        self._kernels.shrink_step(self._state, u, x, move_before, move_after, *self._advance(), out,
                                  self._kernels.NOWHERE if near is None else near)
        return out

    def _advance(self) -> tuple[int, float, float, float, bool]:
        """The next sample's count, averaging weights (mean and variance, frame noise), pull factor and whether it
        pulls: the scalar arguments of the compiled step."""
        self.n += 1
        a = max(1.0 / self.n, self.floor)
        b = max(1.0 / max(self.n - 1, 1), self.floor)
        return self.n, a, b, self.c, self.n > self.warm


def shared_markers(basis: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """How much two directions ``axes[:, i]``, ``axes[:, j]`` of the weights move the same markers: the cosine of
    their per-marker displacement energies (``basis``: 3n x m, x, y, z per marker), 1 on the diagonal, 0 for
    directions that move disjoint markers. Why: NoiseShrink's pull on a direction is let go while the face moves, but
    only a move on its own markers says its own part may be signal: a blink's well-seen part lets its ill-seen part
    go (both move the eyelids), a talking mouth does not let the eyes' ill-seen directions go (issue 41, ICT 0.2 mm:
    with the face's largest move, apfel's eyeWide / eyeLookUp directions jittered 6 x the truth's; docs/robustness.md,
    "the streamed default's jitter against `a2f`")."""
    D = np.asarray(basis, dtype=np.float64) @ np.asarray(axes, dtype=np.float64)
    e = (D.reshape(-1, 3, D.shape[1]) ** 2).sum(1)
    e = e / np.maximum(np.linalg.norm(e, axis=0), 1e-300)
    near = np.clip(e.T @ e, 0.0, 1.0)
    np.fill_diagonal(near, 1.0)
    return near


class RotatedIMM:
    """An IMMFilter over the coordinates ``u = V' y`` of an orthonormal basis ``V`` (``axes``, columns), output
    rotated back. Why: weights from one least-squares fit carry correlated noise, covariance ``sigma^2 C`` with
    ``C`` the fit's inverse Hessian; shapes the markers tell apart badly (eyeWide / eyeLookUp) are noisy in their
    difference, not in their sum. Along ``C``'s eigenvectors the noise is independent, so each direction gets its
    own variance (``set_noise(along(cov))``: the diagonal of ``V' cov V``) and its own hold / move decision: the
    ill-seen directions are held hard while the well-seen ones (a blink, the jaw) follow at once. A per-shape
    IMM can only take the diagonal of ``C``, which smooths every direction of a noisy shape alike. The
    constant-velocity models' process noise is isotropic, so a rotation leaves it as it is."""

    latency_frames = 0

    def __init__(self, axes: np.ndarray | None, imm: IMMFilter, shrink: NoiseShrink | None = None,
                 share: float = 0.0, near: np.ndarray | None = None) -> None:
        """``axes`` None: the shapes' own axes (no rotation), where two m x m products a frame cost more than the
        rotation is worth (1000-shape rigs: ~1 ms of a 2 ms budget, docs/performance.md). ``shrink``: each
        direction's output pulled toward its running mean where the stream shows it carries mostly noise.
        ``share``: after each step every direction's 'move' probability is at least this fraction of the largest
        one. Why: the directions are one face's; a blink the fit spreads over a well-seen direction and an ill-seen
        one moves both at once, but the ill-seen one alone cannot tell its part from noise and its hold model flattens
        the peak (issue 41, MakeHuman 0.5 mm: blink retention 0.89 -> 0.91 at 0.3). ``near`` (directions x
        directions, ``shared_markers``): the pull on direction i let go by the largest ``near[i, j]`` x direction j's
        'move' probability rather than the face's largest (None: the face's)."""
        self.axes = None if axes is None else np.asarray(axes, dtype=np.float64)
        if self.axes is not None and (self.axes.ndim != 2 or self.axes.shape[0] != self.axes.shape[1]):
            raise ValueError(f"RotatedIMM axes must be a square matrix, got shape {self.axes.shape}")
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"RotatedIMM share must lie in [0, 1], got {share}")
        self.imm = imm
        self.shrink = shrink
        self.share = float(share)
        self.near = None if near is None else np.ascontiguousarray(near, dtype=np.float64)
        if self.near is not None and (self.near.ndim != 2 or self.near.shape[0] != self.near.shape[1]):
            raise ValueError(f"RotatedIMM near must be directions x directions, got shape {self.near.shape}")
        self._before: np.ndarray | None = None  # the compiled step's scratch: 'move' probabilities before it

    def reset(self) -> None:
        self.imm.reset()
        if self.shrink is not None:
            self.shrink.reset()

    @property
    def r(self) -> np.ndarray:
        """The measurement variance per direction."""
        return self.imm.r

    def along(self, cov: np.ndarray) -> np.ndarray:
        if self.axes is None:
            return np.maximum(np.diag(np.asarray(cov, dtype=np.float64)).copy(), 1e-300)
        return variances_along(self.axes, cov)

    def set_noise(self, r: np.ndarray) -> None:
        """The measurement variance per direction (``along`` of the noise's covariance), the state kept."""
        self.imm.set_noise(r)

    def step(self, y: np.ndarray) -> np.ndarray:
        y = np.asarray(y, dtype=np.float64)
        u = np.ascontiguousarray(y) if self.axes is None else self.axes.T @ y
        imm, shrink = self.imm, self.shrink
        if shrink is not None and shrink._state is not None and imm._state is not None and u.size == imm._all.size:
            # streamed kalman's every frame after the first: the IMM, the shared regime and the pull in one compiled
            # call (solvers.imm_kernels.shared_shrunk_step; as three calls with their copies ~11 us at 53 directions)
            if self._before is None or self._before.size != u.size:
                self._before = np.empty(u.size)
            x = np.empty(u.size)
            imm._kernels.shared_shrunk_step(imm._state, u, imm._all, imm.transition, self.share, shrink._state,
                                            *shrink._advance(), self._before, x,
                                            imm._kernels.NOWHERE if self.near is None else self.near)
            return x if self.axes is None else self.axes @ x
        started = imm.move_probability is not None
        before = imm.move_probability.copy() if started and shrink is not None else None
        x = imm.step(u)
        if started and self.share > 0:
            imm.share_move(self.share, x)
        if shrink is not None:  # the first sample starts both
            x = shrink.step(u, np.zeros(u.size) if before is None else before, x,
                            imm.move_probability if started else np.zeros(u.size), self.near)
        return x if self.axes is None else self.axes @ x
