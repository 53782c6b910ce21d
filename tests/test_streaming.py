"""Streaming movement matching: sliding window, lookahead, missing markers, limits, drift."""

from __future__ import annotations

import numpy as np
import pytest

from solvers.movement import MovementMatching
from solvers.prior import PCAPrior
from solvers.streaming import StreamingMovement
from tests.test_movement import smooth_weights


@pytest.fixture(scope="module")
def take(demo):
    rig, layout = demo
    B = layout.basis(rig)
    rng = np.random.default_rng(11)
    T, n, m = 400, layout.n_markers, rig.n_shapes
    truth = smooth_weights(rng, T, m, width=12) * (rng.random(m) < 0.3)  # a few shapes active at a time
    S = (truth @ B.T).reshape(T, n, 3) + rng.normal(0, 0.3, (T, n, 3))
    return B, truth, S, PCAPrior.from_shapes(B)


def test_long_window_and_lookahead_approach_the_offline_solve(take):
    B, _, S, prior = take
    kw = dict(alpha=0.5, prior=prior, beta=0.1)
    offline = MovementMatching(B, start="free", end="free", **kw).solve(S)
    gaps = []
    for K, L in [(2, 0), (16, 0), (16, 8), (96, 48)]:
        W = StreamingMovement(B, window=K, lookahead=L, limits="none", **kw).solve(S)
        assert W.shape == offline.shape
        gaps.append(np.abs(W[50:] - offline[50:]).mean())
    assert gaps[0] > gaps[1] > gaps[2] > gaps[3]
    assert gaps[3] < 1e-4 * np.abs(offline).mean() + 1e-9


def test_with_no_prior_or_limits_the_stream_is_the_per_frame_fit(take):
    """Seol §4 again: exact movement matching with a free right end reproduces per-frame LS."""
    B, _, S, _ = take
    per_frame = np.linalg.lstsq(B, S.reshape(len(S), -1).T, rcond=None)[0].T
    W = StreamingMovement(B, window=8, beta=0.05, limits="none").solve(S)
    assert np.allclose(W, per_frame, atol=1e-5)


def test_step_outputs_frame_t_minus_lookahead(take):
    B, _, S, prior = take
    st = StreamingMovement(B, window=12, lookahead=5, alpha=0.5, prior=prior)
    stepped = np.array([st.step(s) for s in S])
    aligned = st.solve(S)
    assert np.allclose(stepped[5:], aligned[:-5])
    st.reset()
    assert np.array_equal(np.array([st.step(s) for s in S]), stepped)  # reset forgets everything


def test_missing_markers_and_nans_never_give_nan(take):
    B, truth, S, prior = take
    rng = np.random.default_rng(0)
    T, n = S.shape[:2]
    valid = rng.random((T, n)) > 0.1
    valid[100:110] = False  # every marker gone for a while
    valid[200:260, :5] = False
    X = S.copy()
    X[~valid] = np.nan
    st = StreamingMovement(B, np.zeros(B.shape[1]), np.ones(B.shape[1]), window=16, lookahead=2, alpha=0.5,
                           prior=prior, beta=0.1)
    W = np.array([st.step(X[i], valid[i]) for i in range(T)])
    assert np.isfinite(W).all()
    W2 = np.array([st.step(X[i], np.ones(n, bool)) for i in range(T)])  # NaN with valid=True: still fine
    assert np.isfinite(W2).all()
    full = StreamingMovement(B, np.zeros(B.shape[1]), np.ones(B.shape[1]), window=16, lookahead=2, alpha=0.5,
                             prior=prior, beta=0.1).solve(S)
    W3 = StreamingMovement(B, np.zeros(B.shape[1]), np.ones(B.shape[1]), window=16, lookahead=2, alpha=0.5,
                           prior=prior, beta=0.1).solve(X, valid)
    ok = np.r_[0:95, 130:195, 270:T]  # away from the big gaps the stream recovers the full-data result
    assert np.abs(W3[ok] - full[ok]).mean() < 0.25 * np.abs(full - truth).mean()


def test_weights_respect_the_rig_limits(take):
    B, _, S, prior = take
    m = B.shape[1]
    lo, hi = np.zeros(m), np.full(m, 0.6)
    W = StreamingMovement(B, lo, hi, window=10, alpha=0.1, prior=prior, beta=0.1).solve(3 * S)
    assert W.min() >= 0.0 and W.max() <= 0.6


def test_no_drift_over_a_long_stream(demo):
    """Three minutes at 60 Hz: the error in the last minute is no larger than in the first."""
    rig, layout = demo
    B = layout.basis(rig)
    rng = np.random.default_rng(5)
    rate, T, n, m = 60.0, 3 * 60 * 60, layout.n_markers, rig.n_shapes
    truth = smooth_weights(rng, T, m, width=6) * (rng.random((T // 600 + 1, m)) < 0.3).repeat(600, 0)[:T]
    S = (truth @ B.T).reshape(T, n, 3) + rng.normal(0, 0.3, (T, n, 3))
    valid = rng.random((T, n)) > 0.02
    st = StreamingMovement(B, rig.lower, rig.upper, window=16, lookahead=0, alpha=1.0,
                           prior=PCAPrior.from_shapes(B), beta=0.1)
    W = st.solve(S, valid)
    err = np.sqrt(np.mean((W - truth) ** 2, axis=1))
    first, last = np.sqrt(np.mean(err[: int(rate * 60)] ** 2)), np.sqrt(np.mean(err[-int(rate * 60):] ** 2))
    assert np.isfinite(W).all()
    assert last < 1.2 * first


def test_rejects_bad_windows(take):
    B = take[0]
    for K, L in [(0, 0), (4, 4), (4, -1)]:
        with pytest.raises(ValueError):
            StreamingMovement(B, window=K, lookahead=L)


def _literal_window(B, S_win, w_left, *, alpha, prior, beta, mw2):
    """Seol §4/§7.1 on one window, solved densely: K free frames after the fixed boundary frame
    (the Appendix's known rows moved to the right-hand side), free right end; no decoupling."""
    K, m = len(S_win) - 1, B.shape[1]
    rw = np.repeat(mw2, 3)
    G, Kp = B.T @ B, alpha * prior.precision + beta * B.T @ (rw[:, None] * B)
    Lap = 2.0 * np.eye(K) - np.eye(K, k=1) - np.eye(K, k=-1)
    Lap[-1, -1] = 1.0
    A = np.kron(Lap, G) + np.kron(np.eye(K), Kp)
    ds = np.diff(S_win, axis=0)  # ds[tau - 1] = s_tau - s_{tau - 1}, tau = 1..K
    r = (ds - np.vstack([ds[1:], np.zeros((1, ds.shape[1]))])) @ B + beta * (S_win[1:] * rw) @ B
    r += alpha * prior.gradient_constant()
    r[0] += G @ w_left
    return np.linalg.solve(A, r.ravel()).reshape(K, m)


@pytest.mark.parametrize("K, L, limits, weighted", [(6, 0, "clip", False), (8, 3, "clip", True),
                                                    (5, 4, "none", False), (1, 0, "clip", False)])
def test_each_published_frame_is_the_literal_window_solve(take, K, L, limits, weighted):
    """The prefactored, fused per-frame step equals re-solving the K-frame window from scratch with
    the published (clipped) frame t-K as its boundary, frame after frame."""
    B, _, S, prior = take
    T, n, m = 40, S.shape[1], B.shape[1]
    mw2 = np.random.default_rng(1).uniform(0.5, 2.0, n) ** 2 if weighted else np.ones(n)
    lo, hi = np.full(m, -0.05), np.full(m, 0.5)
    st = StreamingMovement(B, lo, hi, window=K, lookahead=L, alpha=0.3, prior=prior, beta=0.2,
                           marker_weights=np.sqrt(mw2) if weighted else None, limits=limits)
    X = S[:T].reshape(T, -1)
    out = np.array([st.step(S[i]) for i in range(T)])  # out[t] is frame t - L
    for t in range(K + L, T):
        w_left = out[t - K + L]  # frame t - K as published
        Y = _literal_window(B, X[t - K:t + 1], w_left, alpha=0.3, prior=prior, beta=0.2, mw2=mw2)
        expect = np.clip(Y[K - 1 - L], lo, hi) if limits == "clip" else Y[K - 1 - L]
        assert np.allclose(out[t], expect, atol=1e-9 * max(1.0, np.abs(expect).max())), t


def test_nan_coordinates_behave_like_missing_markers(take):
    """The per-frame path finds NaN/inf from the projection alone; the result must be exactly that
    of declaring those markers missing."""
    B, _, S, prior = take
    T, n = 120, S.shape[1]
    rng = np.random.default_rng(3)
    valid = rng.random((T, n)) > 0.05
    valid[40:45, :3] = False
    X = S[:T].copy()
    X[~valid] = np.nan
    X[50, 2, 1] = np.inf
    valid[50, 2] = False
    kw = dict(window=10, lookahead=2, alpha=0.5, prior=prior, beta=0.1)
    a = StreamingMovement(B, np.zeros(B.shape[1]), np.ones(B.shape[1]), **kw)
    b = StreamingMovement(B, np.zeros(B.shape[1]), np.ones(B.shape[1]), **kw)
    Wa = np.array([a.step(X[i]) for i in range(T)])
    Wb = np.array([b.step(np.where(valid[i][:, None], S[i], 0.0), valid[i]) for i in range(T)])
    assert np.isfinite(Wa).all()
    assert np.array_equal(Wa, Wb)


def test_step_keeps_no_reference_to_the_callers_buffers(take):
    """A live source may reuse one array for every frame: the result must not change."""
    B, _, S, prior = take
    kw = dict(window=8, lookahead=2, alpha=0.5, prior=prior, beta=0.1)
    valid = np.ones(S.shape[:2], bool)
    valid[20:25, :3] = False  # gaps opening after complete frames
    valid[50:52, 5] = False
    a, b = StreamingMovement(B, **kw), StreamingMovement(B, **kw)
    frame, vis = np.empty_like(S[0]), np.empty(S.shape[1], bool)
    Wa, Wb = [], []
    for i in range(80):
        Wa.append(a.step(S[i].copy(), valid[i].copy()))
        frame[:], vis[:] = S[i], valid[i]
        w = b.step(frame, vis)
        Wb.append(w.copy())
        w[:] = 99.0  # the caller may also scribble on the returned weights
    assert np.array_equal(np.array(Wa), np.array(Wb))
