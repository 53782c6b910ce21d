"""l1 trend filter (solvers/trend.py) against an independent solver of its dual, and on a blink."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import lsq_linear

from livecap.offline.metrics import jitter
from solvers.trend import TrendFilter, second_difference, second_difference_t


def dual_solution(y: np.ndarray, lam: float) -> np.ndarray:
    """x = y - D2^T v with v = argmin |D2^T v - y|^2, |v| <= lam (Kim et al. 2009 §5: the dual), by scipy."""
    n = len(y)
    Dt = second_difference_t(np.eye(n - 2), n)
    v = lsq_linear(Dt, y, bounds=(-lam, lam), tol=1e-12, method="bvls").x
    return y - Dt @ v


@settings(max_examples=40, deadline=None)
@given(st.integers(5, 40), st.floats(0.01, 5.0), st.integers(0, 2**31 - 1))
def test_matches_the_dual_solved_independently(n, lam, seed):
    rng = np.random.default_rng(seed)
    y = np.cumsum(rng.normal(size=n)) + rng.normal(size=n)
    tf = TrendFilter(lam, tol=1e-9, max_iter=200_000)
    x = tf.filter(y)
    assert tf.converged
    assert np.allclose(x, dual_solution(y, lam), atol=1e-5)


def test_unconverged_is_reported():
    y = np.cumsum(np.random.default_rng(1).normal(size=200))
    tf = TrendFilter(1.0, tol=1e-12, max_iter=3)
    tf.filter(y)
    assert not tf.converged and tf.iterations == 3


def test_a_line_is_kept_and_zero_channels_are_untouched():
    t = np.arange(50.0)
    Y = np.stack([3.0 - 0.2 * t, np.zeros(50), np.sin(t)], axis=1)
    X = TrendFilter(np.array([5.0, 5.0, 0.0])).filter(Y)
    assert np.allclose(X[:, 0], Y[:, 0], atol=1e-6)
    assert np.array_equal(X[:, 1:], Y[:, 1:])  # all-zero channel, and lam 0 means no filtering


def test_noisy_blink_loses_jitter_not_its_peak():
    """Kinks stay where the data put them: the noise's second differences go, the peak stays."""
    rng = np.random.default_rng(0)
    t = np.arange(240)
    truth = np.where(np.abs(t - 120) < 15, 0.5 + 0.5 * np.cos(np.pi * (t - 120) / 15), 0.0)
    sd = 0.02
    y = truth + rng.normal(scale=sd, size=len(t))
    x = TrendFilter(10 * sd).filter(y)
    assert jitter(y) / jitter(truth) > 15  # measured 22
    assert jitter(x) / jitter(truth) < 1.5  # measured 0.89
    assert x[105:136].max() > 0.9  # measured 1.02
    assert np.abs(second_difference(x)).max() > 0.01  # kinks remain (not a straight line)


def constrained_solution(y: np.ndarray, lam: float, fixed: np.ndarray) -> np.ndarray:
    """The fixed-frame problem as a QP in (x_free, t) by quadprog: min |x - y|^2 / 2 + lam sum t,
    -t <= D2 x <= t, x = y on fixed frames (t gets a 1e-9 quadratic so the QP is strictly convex)."""
    from quadprog import solve_qp

    n = len(y)
    D = second_difference(np.eye(n))
    F = np.flatnonzero(~fixed)
    b0 = D[:, fixed] @ y[fixed]
    DF = D[:, F]
    k, r = len(F), len(D)
    G = np.diag(np.r_[np.ones(k), np.full(r, 1e-9)])
    a = np.r_[y[F], -lam * np.ones(r)]
    C = np.block([[-DF, np.eye(r)], [DF, np.eye(r)]])  # t - D x >= b0, t + D x >= -b0
    sol = solve_qp(G, a, C.T, np.r_[b0, -b0])[0]
    x = y.copy()
    x[F] = sol[:k]
    return x


@settings(max_examples=25, deadline=None)
@given(st.integers(8, 30), st.floats(0.05, 3.0), st.integers(0, 2**31 - 1))
def test_fixed_frames_match_a_constrained_qp(n, lam, seed):
    rng = np.random.default_rng(seed)
    y = np.cumsum(rng.normal(size=n))
    fixed = rng.random(n) < 0.3
    fixed[[0, -1]] = True
    x = TrendFilter(lam, tol=1e-9, max_iter=200_000).filter(y, fixed=fixed)
    assert np.array_equal(x[fixed], y[fixed])
    assert np.allclose(x, constrained_solution(y, lam, fixed), atol=1e-4)
