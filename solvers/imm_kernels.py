"""Compiled (numba) kernels of the two-model IMM weight filter (``solvers.tracking.IMMFilter``).

Why compiled: per channel a step is a few dozen scalar operations (Bar-Shalom, Li & Kirubarajan 2001
§11.6.6: interaction/mixing, mode-matched DWNA constant-velocity filtering, mode probability update,
combination). As whole-array numpy calls it cost ~40 calls a frame, i.e. per-call overhead at a face
rig's 50-150 channels (docs/performance.md, "Compiled kernels (numba)"); here one loop over channels
keeps each channel's state in registers. A whole take's curves run in one call (frames inside).

The state is one (``N_STATE``, channels) array, rows named below; the numbers equal the whole-array
version's to rounding (tests/test_tracking.py compares it with the numpy reference in tests/).
``cache=True`` keeps the machine code in ``__pycache__`` so only a process's first run compiles.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# rows of the state: (value, velocity) and covariance (p00, p01, p11) of the 'hold' and 'move' models,
# mode probabilities, measurement variance, DWNA process-noise intensities
XH, VH, XM, VM, P00H, P01H, P11H, P00M, P01M, P11M, MU_HOLD, MU_MOVE, R, Q_HOLD, Q_MOVE = range(15)
N_STATE = 15
_TWO_PI = 2 * np.pi


@numba.njit(cache=True, nogil=True, inline="always")
def _matched(x, v, p00, p01, p11, q, r, y, ok):
    """One mode-matched constant-velocity Kalman step (DWNA ``Q = q G G'``, ``G = (1/2, 1)``) from the mixed
    state; returns the state and the innovation likelihood (1 when the sample is missing: no update)."""
    x = x + v
    p00, p01 = p00 + 2.0 * p01 + p11 + q / 4, p01 + p11 + q / 2
    p11 = p11 + q
    s = p00 + r
    if not ok:
        return x, v, p00, p01, p11, 1.0
    e = y - x
    k0, k1 = p00 / s, p01 / s
    x, v = x + k0 * e, v + k1 * e
    p11 = p11 - k1 * p01
    f = r / s  # 1 - k0
    return x, v, p00 * f, p01 * f, p11, math.exp(e * e / s * -0.5) / math.sqrt(s * _TWO_PI)


@numba.njit(cache=True, nogil=True, inline="always")
def _channel(st, i, y, ok, s00, s01, s10, s11):
    """Channel ``i``'s IMM step in place; returns the combined output. With two models the mixing is closed
    form: ``a_j = P(hold before | j now)``, mixed mean ``x_move + a_j d``, spread term ``a_j (1 - a_j) d d'``."""
    mu0, mu1 = st[MU_HOLD, i], st[MU_MOVE, i]
    c0, c1 = s00 * mu0 + s10 * mu1, s01 * mu0 + s11 * mu1
    a0, a1 = s00 * mu0 / c0, s01 * mu0 / c1
    b0, b1 = a0 - a0 * a0, a1 - a1 * a1
    xm, vm, pm0, pm1, pm2 = st[XM, i], st[VM, i], st[P00M, i], st[P01M, i], st[P11M, i]
    d0, d1 = st[XH, i] - xm, st[VH, i] - vm
    dd0, dd1, dd2 = d0 * d0, d0 * d1, d1 * d1
    dp0, dp1, dp2 = st[P00H, i] - pm0, st[P01H, i] - pm1, st[P11H, i] - pm2
    r = st[R, i]
    x0, v0, h00, h01, h11, l0 = _matched(a0 * d0 + xm, a0 * d1 + vm, a0 * dp0 + pm0 + b0 * dd0,
                                         a0 * dp1 + pm1 + b0 * dd1, a0 * dp2 + pm2 + b0 * dd2, st[Q_HOLD, i], r, y, ok)
    x1, v1, m00, m01, m11, l1 = _matched(a1 * d0 + xm, a1 * d1 + vm, a1 * dp0 + pm0 + b1 * dd0,
                                         a1 * dp1 + pm1 + b1 * dd1, a1 * dp2 + pm2 + b1 * dd2, st[Q_MOVE, i], r, y, ok)
    mu0, mu1 = c0 * l0 + 1e-300, c1 * l1 + 1e-300
    total = mu0 + mu1
    mu0, mu1 = mu0 / total, mu1 / total
    st[XH, i], st[VH, i], st[P00H, i], st[P01H, i], st[P11H, i] = x0, v0, h00, h01, h11
    st[XM, i], st[VM, i], st[P00M, i], st[P01M, i], st[P11M, i] = x1, v1, m00, m01, m11
    st[MU_HOLD, i], st[MU_MOVE, i] = mu0, mu1
    return mu0 * x0 + mu1 * x1


@numba.njit(cache=True, nogil=True)
def imm_step(st: np.ndarray, y: np.ndarray, ok: np.ndarray, transition: np.ndarray, out: np.ndarray) -> None:
    """One frame: ``st`` (N_STATE, C) updated in place, the output into ``out`` (C); ``ok`` False: predict only."""
    s00, s01, s10, s11 = transition[0, 0], transition[0, 1], transition[1, 0], transition[1, 1]
    for i in range(y.shape[0]):
        out[i] = _channel(st, i, y[i], ok[i], s00, s01, s10, s11)


@numba.njit(cache=True, nogil=True)
def imm_take(st: np.ndarray, Y: np.ndarray, ok: np.ndarray, transition: np.ndarray, out: np.ndarray) -> None:
    """Frames ``Y`` (T, C) in order from state ``st``: the same numbers as ``imm_step`` frame by frame."""
    s00, s01, s10, s11 = transition[0, 0], transition[0, 1], transition[1, 0], transition[1, 1]
    for t in range(Y.shape[0]):
        for i in range(Y.shape[1]):
            out[t, i] = _channel(st, i, Y[t, i], ok[t, i], s00, s01, s10, s11)


NOWHERE = np.zeros((0, 0))  # ``near`` empty: every channel's pull let go by the face's largest 'move' probability


@numba.njit(cache=True, nogil=True, inline="always")
def _top(mu: np.ndarray, near: np.ndarray, i: int) -> float:
    """The largest 'move' probability that lets channel ``i``'s pull go: over all channels (``near`` empty or
    ``i`` < 0), else the largest of ``near[i, j] mu[j]`` (``near[i, i]`` = 1)."""
    top = 0.0
    if near.shape[0] == 0 or i < 0:
        for j in range(mu.shape[0]):
            top = max(top, mu[j])
        return top
    for j in range(mu.shape[0]):
        top = max(top, near[i, j] * mu[j])
    return top


# rows of the NoiseShrink state (``solvers.tracking.NoiseShrink``): running mean, variance, frame-noise variance,
# last sample
S_MEAN, S_VAR, S_NOISE, S_LAST = range(4)
N_SHRINK = 4


@numba.njit(cache=True, nogil=True)
def shrink_step(st: np.ndarray, u: np.ndarray, x: np.ndarray, move_before: np.ndarray, move_after: np.ndarray,
                n: int, a: float, b: float, c: float, pull: bool, out: np.ndarray, near: np.ndarray) -> None:
    """One frame of ``NoiseShrink``: the statistics updated with sample ``u`` (the frame noise only where the
    direction held, ``move_before`` < 0.5), then, if ``pull``, the IMM's output ``x`` pulled toward the mean by
    ``g = clip(1 - c noise / var, 0, 1)``, let go by the largest ``move_after`` (``near``: by the largest of
    ``near[i] * move_after``, see ``_top``); into ``out``."""
    C = u.shape[0]
    if n == 1:
        for i in range(C):
            st[S_MEAN, i], st[S_VAR, i], st[S_NOISE, i], st[S_LAST, i] = u[i], 0.0, 0.0, u[i]
            out[i] = x[i]
        return
    top = _top(move_after, near, -1)
    for i in range(C):
        d = u[i] - st[S_MEAN, i]
        m = st[S_MEAN, i] + a * d
        v = (1.0 - a) * (st[S_VAR, i] + a * d * d)
        e = u[i] - st[S_LAST, i]
        if move_before[i] < 0.5:
            st[S_NOISE, i] += b * (0.5 * e * e - st[S_NOISE, i])
        st[S_MEAN, i], st[S_VAR, i], st[S_LAST, i] = m, v, u[i]
        if pull:
            g = 1.0 - c * st[S_NOISE, i] / max(v, 1e-30)
            g = min(max(g, 0.0), 1.0)
            g += (1.0 - g) * (top if near.shape[0] == 0 else _top(move_after, near, i))
            out[i] = m + g * (x[i] - m)
        else:
            out[i] = x[i]


@numba.njit(cache=True, nogil=True)
def share_move(st: np.ndarray, share: float, out: np.ndarray) -> None:
    """After a step: every channel's 'move' probability raised to at least ``share`` x the largest one, and the
    output ``out`` recombined from the two models' values with it (channels of one face share its regime)."""
    top = 0.0
    for i in range(st.shape[1]):
        top = max(top, st[MU_MOVE, i])
    floor = share * top
    for i in range(st.shape[1]):
        mu = max(st[MU_MOVE, i], floor)
        st[MU_MOVE, i], st[MU_HOLD, i] = mu, 1.0 - mu
        out[i] = (1.0 - mu) * st[XH, i] + mu * st[XM, i]


@numba.njit(cache=True, nogil=True)
def shared_shrunk_step(st: np.ndarray, y: np.ndarray, ok: np.ndarray, transition: np.ndarray, share: float,
                       shrink: np.ndarray, n: int, a: float, b: float, c: float, pull: bool, before: np.ndarray,
                       out: np.ndarray, near: np.ndarray) -> None:
    """``imm_step``, then ``share_move`` (if ``share`` > 0), then ``shrink_step`` on its output, in one call: the
    streamed weight stage's three kernels and the 'move' probabilities kept between them, the same numbers as the
    three calls (``before``: scratch of C). One call a frame instead of three and their copies (issue 39)."""
    for i in range(y.shape[0]):
        before[i] = st[MU_MOVE, i]
    imm_step(st, y, ok, transition, out)
    if share > 0:
        share_move(st, share, out)
    shrink_step(shrink, y, out, before, st[MU_MOVE], n, a, b, c, pull, out, near)
