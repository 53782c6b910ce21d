"""The 1€ filter against the paper's pseudo-code, the fixed-lag smoother, the solver wrapper."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.filters import CausalPolyFilter, FilteredSolver, FixedLagSmoother, OneEuroFilter, endpoint_weights


class PaperOneEuro:
    """A literal scalar transcription of Casiez et al. 2012's pseudo-code (LowPassFilter + OneEuroFilter)."""

    class LowPass:
        def __init__(self):
            self.first = True
            self.hatxprev = 0.0
            self.xprev = 0.0

        def filter(self, x, alpha):
            if self.first:
                self.first = False
                hatx = x
            else:
                hatx = alpha * x + (1 - alpha) * self.hatxprev
            self.xprev = x
            self.hatxprev = hatx
            return hatx

    def __init__(self, rate, mincutoff, beta, dcutoff):
        self.rate, self.mincutoff, self.beta, self.dcutoff = rate, mincutoff, beta, dcutoff
        self.x, self.dx = self.LowPass(), self.LowPass()

    def alpha(self, cutoff):
        tau = 1.0 / (2 * math.pi * cutoff)
        te = 1.0 / self.rate
        return 1.0 / (1.0 + tau / te)

    def filter(self, x):
        dx = 0.0 if self.x.first else (x - self.x.xprev) * self.rate
        edx = self.dx.filter(dx, self.alpha(self.dcutoff))
        cutoff = self.mincutoff + self.beta * abs(edx)
        return self.x.filter(x, self.alpha(cutoff))


def sampled_signal(n=600, rate=120.0, seed=3):
    t = np.arange(n) / rate
    rng = np.random.default_rng(seed)
    clean = np.sin(2 * np.pi * 0.7 * t) + (t > 2.5) * 0.8
    return clean[:, None] + rng.normal(0, 0.05, (n, 3))


def test_one_euro_matches_paper_pseudocode_per_channel():
    X = sampled_signal()
    mincut, beta, dcut = np.array([0.5, 1.0, 2.0]), np.array([0.0, 0.3, 5.0]), np.array([1.0, 1.0, 3.0])
    got = OneEuroFilter(120.0, mincut, beta, dcut).filter(X)
    for c in range(3):
        ref = PaperOneEuro(120.0, mincut[c], beta[c], dcut[c])
        want = np.array([ref.filter(x) for x in X[:, c]])
        np.testing.assert_allclose(got[:, c], want, rtol=0, atol=1e-12)


def test_one_euro_reduces_jitter_and_speed_reduces_lag():
    X = sampled_signal()
    still = OneEuroFilter(120.0, 1.0, 0.0).filter(X)
    assert np.abs(np.diff(still, 2, axis=0)).mean() < 0.2 * np.abs(np.diff(X, 2, axis=0)).mean()
    ramp = np.arange(400.0)[:, None] * 0.01  # constant speed 1.2 units/s
    for beta in (0.0, 1.0):
        f = OneEuroFilter(120.0, 1.0, beta)
        y = f.filter(ramp)
        lag = (ramp[-1, 0] - y[-1, 0]) / 0.01  # frames behind, steady state
        alpha = 1 / (1 + f.latency_frames(1.2 * (beta > 0))[()])
        assert abs(lag - (1 - alpha) / alpha) < 1e-6
    assert OneEuroFilter(120.0, 1.0, 1.0).latency_frames(1.2) < OneEuroFilter(120.0, 1.0, 0.0).latency_frames(1.2)


def test_one_euro_missing_channel_holds_and_never_nan():
    f = OneEuroFilter(120.0, 1.0, 0.5, reinit_after=5)
    first = f.step(np.array([1.0, 2.0]), np.array([True, False]))
    assert np.isfinite(first).all()
    held = f.step(np.array([np.nan, 3.0]), np.array([False, True]))
    assert held[0] == first[0] and held[1] == 3.0  # channel 1 starts at its first real sample
    for _ in range(6):
        f.step(np.array([0.0, 3.0]), np.array([False, True]))
    assert f.step(np.array([9.0, 3.0]), np.array([True, True]))[0] == 9.0  # stale after 6 missing: restart


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 6), st.floats(-2, 2), st.floats(-1, 1), st.floats(-0.1, 0.1))
def test_fixed_lag_smoother_is_exact_on_quadratics(lag, a, b, c):
    t = np.arange(60.0)
    x = (a + b * t + c * t * t)[:, None]
    f = FixedLagSmoother(lag)
    y = np.array([f.step(v) for v in x])
    np.testing.assert_allclose(y[2 * lag:], x[lag:-lag], atol=1e-6 * (1 + np.abs(x).max()))
    np.testing.assert_allclose(f.filter(x), x, atol=1e-6 * (1 + np.abs(x).max()))
    assert f.latency_frames == lag


def test_fixed_lag_smoother_bridges_missing_samples_and_smooths():
    rng = np.random.default_rng(0)
    t = np.arange(300.0)
    clean = np.sin(t / 30.0)[:, None]
    x = clean + rng.normal(0, 0.05, clean.shape)
    ok = rng.random(clean.shape) > 0.2
    y = FixedLagSmoother(6).filter(np.where(ok, x, 1e6), ok)  # missing values are never used
    assert np.isfinite(y).all()
    assert np.sqrt(np.mean((y - clean) ** 2)) < 0.6 * np.sqrt(np.mean((x - clean) ** 2))


class _Echo:
    """Unit-test stand-in for a solver: returns the x coordinate of the first two markers."""

    def __init__(self):
        self.lower, self.upper, self.resets = np.zeros(2), np.ones(2), 0

    def step(self, target, valid):
        return target[:2, 0].copy()

    def reset(self):
        self.resets += 1


def test_filtered_solver_filters_weights_clips_and_resets():
    inner = _Echo()
    fs = FilteredSolver(inner, weight_filter=FixedLagSmoother(2))
    assert fs.latency_frames == 2
    outs = [fs.step(np.full((3, 3), v), np.ones(3, bool)) for v in (0.2, 0.4, 0.6, 0.8, 2.0)]
    assert all(((o >= 0) & (o <= 1)).all() for o in outs)
    fs.reset()
    assert inner.resets == 1
    fm = FilteredSolver(_Echo(), marker_filter=OneEuroFilter(120.0, 0.5))
    fm.step(np.zeros((3, 3)), np.ones(3, bool))
    assert fm.step(np.ones((3, 3)), np.ones(3, bool))[0] < 0.2


@settings(max_examples=25, deadline=None)
@given(st.integers(4, 20), st.floats(-3, 3), st.floats(-0.2, 0.2), st.floats(-0.01, 0.01))
def test_causal_poly_filter_has_no_lag_on_quadratics(window, a, b, c):
    t = np.arange(60, dtype=float)
    x = (a + b * t + c * t * t)[:, None] * np.ones((1, 2))
    y = CausalPolyFilter(window).filter(x)
    np.testing.assert_allclose(y[window:], x[window:], atol=1e-7)  # exact once the window is full


def test_causal_poly_filter_noise_gain_and_missing_samples():
    f = CausalPolyFilter(12)
    assert math.isclose(f.noise_gain, float(np.sum(endpoint_weights(12) ** 2)))
    for n in (4, 12, 20):  # closed form of the quadratic end-point variance gain
        assert math.isclose(CausalPolyFilter(n).noise_gain, 3 * (3 * n * n - 3 * n + 2) / (n * (n + 1) * (n + 2)))
    rng = np.random.default_rng(0)
    noise = rng.normal(0, 1, (20000, 3))
    assert abs(np.var(f.filter(noise)[20:]) / f.noise_gain - 1) < 0.05
    ok = rng.random((400, 3)) > 0.2
    ok[100:140, 0] = False  # a long gap in one channel
    x = np.sin(np.arange(400) / 20.0)[:, None] * np.ones((1, 3))
    y = f.filter(np.where(ok, x, 1e6), ok)  # missing samples carry garbage that must not leak out
    assert np.isfinite(y).all() and np.abs(y).max() < 2
    np.testing.assert_allclose(y[ok][50:], x[ok][50:], atol=0.02)
    g = CausalPolyFilter(12)
    np.testing.assert_array_equal(np.stack([g.step(x[t], ok[t]) for t in range(400)]), y)  # filter == steps


@settings(max_examples=40, deadline=None)
@given(st.integers(4, 12), st.integers(1, 3), st.integers(0, 2**32 - 1))
def test_causal_poly_filter_partial_windows_are_the_weighted_fit(window, order, seed):
    """The streamed filter where a window is partly seen against a literal least-squares fit of the seen samples."""
    if window < order + 2:
        window = order + 2
    rng = np.random.default_rng(seed)
    T, C = 40, 5
    x = np.cumsum(rng.normal(size=(T, C)), axis=0)
    ok = rng.random((T, C)) > 0.35
    f = CausalPolyFilter(window, order)
    last = np.zeros(C)
    for t in range(T):
        y = f.step(np.where(ok[t], x[t], 1e6), ok[t])  # a missing sample's garbage must not leak
        for c in range(C):
            rows = [s for s in range(max(0, t - window + 1), t + 1) if ok[s, c]]
            if len(rows) == window:
                want = endpoint_weights(window, order) @ x[t - window + 1:t + 1, c]
            elif len(rows) > order:
                V = np.vander(np.array(rows, float) - t, order + 1, increasing=True)
                want = np.linalg.lstsq(V, x[rows, c], rcond=None)[0][0]
            else:
                want = x[t, c] if ok[t, c] else last[c]
            assert abs(y[c] - want) <= 1e-7 * max(1.0, abs(want)), (t, c, len(rows))
        last = np.where(ok[t], y, last)
