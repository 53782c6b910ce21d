"""Regularisation selected from data: noise estimate, GCV, held-out markers, the prior fit."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.regularisation import DEFAULT_GRID, PriorLeastSquares, estimate_noise, gcv_ridge, holdout_ridge


def linear_problem(seed=0, n=40, m=12, frames=300, sigma=0.5):
    """Markers = B w + noise with B of decaying singular values (ill-conditioned like a rig)."""
    rng = np.random.default_rng(seed)
    U, _ = np.linalg.qr(rng.normal(size=(3 * n, m)))
    V, _ = np.linalg.qr(rng.normal(size=(m, m)))
    B = U @ np.diag(np.logspace(1.5, -0.5, m)) @ V.T
    W = np.abs(rng.normal(0, 0.4, (frames, m)))
    S = (W @ B.T + rng.normal(0, sigma, (frames, 3 * n))).reshape(frames, n, 3)
    return B, W, S, np.ones((frames, n), bool)


def ridge_rmse(B, W, S, lam):
    s = S.reshape(len(S), -1)
    est = np.linalg.solve(B.T @ B + lam * np.eye(B.shape[1]), B.T @ s.T).T
    return np.sqrt(np.mean((est - W) ** 2))


def test_noise_estimate_recovers_sigma_under_smooth_motion():
    rng = np.random.default_rng(1)
    t = np.arange(2000) / 120.0
    smooth = 5 * np.sin(2 * np.pi * 0.8 * t)[:, None, None] * np.ones((1, 10, 3))
    for sigma in (0.2, 0.5, 1.0):
        X = smooth + rng.normal(0, sigma, smooth.shape)
        assert abs(estimate_noise(X, np.ones((2000, 10), bool)) / sigma - 1) < 0.08


def test_gcv_is_deterministic_and_lands_near_the_rmse_optimum():
    B, W, S, V = linear_problem()
    a, b = gcv_ridge(B, S, V), gcv_ridge(B, S, V)
    assert a.value == b.value and np.array_equal(a.scores, b.scores)
    errs = [ridge_rmse(B, W, S, lam) for lam in DEFAULT_GRID]
    best = DEFAULT_GRID[int(np.argmin(errs))]
    assert abs(np.log10(a.value / best)) <= 0.75  # within three grid steps (a factor ~5.6)
    assert ridge_rmse(B, W, S, a.value) < 1.15 * min(errs)
    assert ridge_rmse(B, W, S, a.value) < 0.8 * ridge_rmse(B, W, S, 0.0)


def test_holdout_selection_is_deterministic_and_near_optimum():
    B, W, S, V = linear_problem(seed=2)
    a, b = holdout_ridge(B, S, V), holdout_ridge(B, S, V)
    assert a.value == b.value and a.criterion.startswith("5-fold")
    errs = [ridge_rmse(B, W, S, lam) for lam in DEFAULT_GRID]
    assert ridge_rmse(B, W, S, a.value) < 1.25 * min(errs)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000))
def test_prior_fit_without_prior_is_least_squares_within_bounds(seed):
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(30, 6))
    w = rng.uniform(0.2, 0.8, 6)
    s = (B @ w).reshape(10, 3)
    solver = PriorLeastSquares(B, np.zeros(6), np.ones(6))
    np.testing.assert_allclose(solver.step(s, np.ones(10, bool)), w, atol=1e-6)
    valid = np.ones(10, bool)
    valid[rng.choice(10, 3, replace=False)] = False  # 21 rows left: still determined
    np.testing.assert_allclose(solver.step(s, valid), w, atol=1e-6)
    far = solver.step(s * 5 - 3, np.ones(10, bool))
    assert (far >= -1e-12).all() and (far <= 1 + 1e-12).all()
    assert np.isfinite(solver.step(s, np.zeros(10, bool))).all()


def test_rest_pull_keeps_unused_shapes_exactly_at_rest():
    B, W, S, V = linear_problem(seed=4, frames=50)
    W[:, :4] = 0.0
    S = (W @ B.T).reshape(50, -1, 3) + np.random.default_rng(5).normal(0, 0.2, S.shape)
    plain = PriorLeastSquares(B, np.zeros(12), np.full(12, 5.0), ridge=1.0)
    pulled = PriorLeastSquares(B, np.zeros(12), np.full(12, 5.0), ridge=1.0, rest_pull=np.full(12, 40.0))
    Wp = np.array([plain.step(s, v) for s, v in zip(S, V, strict=True)])
    Wq = np.array([pulled.step(s, v) for s, v in zip(S, V, strict=True)])
    assert (Wq[:, :4] == 0).mean() > (Wp[:, :4] == 0).mean()
    assert np.abs(np.diff(Wq[:, :4], 2, axis=0)).mean() < np.abs(np.diff(Wp[:, :4], 2, axis=0)).mean()


def test_tune_profile_stores_selection_in_settings(demo):
    from livecap.calibration.profile import Profile, calibrate
    from livecap.demo.performance import PerformanceSettings, perform
    from livecap.modes.robust import robust_settings, tune_profile
    from livecap.offline.solve import prepare_targets

    rig, layout = demo
    perf = perform(rig, layout, PerformanceSettings(seconds=4.0, occlusion=0.05))
    profile = calibrate(rig, layout, perf.actor_neutral)
    _, S, _, _ = prepare_targets(perf.take, profile)
    tuned = tune_profile(profile, S, perf.take.valid, perf.take.rate)
    assert tuned == tune_profile(profile, S, perf.take.valid, perf.take.rate)  # deterministic
    assert 0.4 < tuned["noise_mm"] < 0.9  # 0.5 mm per coordinate, plus head-pose noise after stabilising
    assert tuned["ridge"] in DEFAULT_GRID and tuned["ridge_gcv"] in DEFAULT_GRID
    assert robust_settings(profile).prior_ridge == tuned["ridge"]
    assert robust_settings(profile, {"ridge": 3.0}).prior_ridge == 3.0
    assert robust_settings(Profile(**{**vars(profile), "settings": {}})).prior_ridge > 0  # untuned: MAP ridge


def sparse_problem(seed=0, frames=300, sigma=0.5):
    """A rig-like linear problem whose weights are mostly exactly zero (shapes at rest)."""
    B, W, _, V = linear_problem(seed=seed, frames=frames, sigma=sigma)
    rng = np.random.default_rng(seed + 100)
    W = W * (rng.random(W.shape) < 0.2)
    S = (W @ B.T + rng.normal(0, sigma, (frames, B.shape[0]))).reshape(frames, -1, 3)
    return B, W, S, V


def test_universal_threshold_and_l1_weights():
    from solvers.sparse_fit import l1_weights, universal_threshold

    assert math.isclose(universal_threshold(53), math.sqrt(2 * math.log(53)))
    B = np.diag([1.0, 2.0, 4.0])
    np.testing.assert_allclose(l1_weights(B, 0.5, 2.0), 2 * 2.0 * 0.5 * np.array([1.0, 2.0, 4.0]))


def test_sparse_fit_keeps_resting_shapes_at_rest_and_hysteresis_keeps_amplitude():
    from solvers.sparse_fit import HysteresisSparseFit, l1_weights, universal_threshold

    B, W, S, V = sparse_problem(seed=3)
    m = B.shape[1]
    z = universal_threshold(m)
    plain = PriorLeastSquares(B, np.zeros(m), np.full(m, 5.0), ridge=0.1)
    hard = HysteresisSparseFit(B, np.zeros(m), np.full(m, 5.0), 0.1, l1_weights(B, 0.5, z), l1_weights(B, 0.5, z))
    hyst = HysteresisSparseFit(B, np.zeros(m), np.full(m, 5.0), 0.1, l1_weights(B, 0.5, z), l1_weights(B, 0.5, 1.0))
    run = {k: np.array([f.step(s, v) for s, v in zip(S, V, strict=True)]) for k, f in
           (("plain", plain), ("hard", hard), ("hyst", hyst))}
    rest = W == 0
    zero = {k: (np.abs(v[rest]) < 1e-9).mean() for k, v in run.items()}
    assert zero["hard"] > 0.85 and zero["hard"] > zero["plain"] + 0.3
    big = W > 0.4
    assert np.mean(run["hyst"][big] / W[big]) > np.mean(run["hard"][big] / W[big])  # less shrinkage once active
    hyst.reset()
    np.testing.assert_array_equal(np.array([hyst.step(s, v) for s, v in zip(S, V, strict=True)]), run["hyst"])


def test_sparse_ridge_selection_is_deterministic_and_near_optimum():
    from solvers.sparse_fit import SPARSE_GRID, holdout_sparse_ridge, l1_weights, universal_threshold

    B, W, S, V = sparse_problem(seed=5)
    m = B.shape[1]
    z = universal_threshold(m)
    lo, hi = np.zeros(m), np.full(m, 5.0)
    a, b = holdout_sparse_ridge(B, S, V, 0.5, z, lo, hi), holdout_sparse_ridge(B, S, V, 0.5, z, lo, hi)
    assert a.value == b.value and np.array_equal(a.scores, b.scores) and a.value in SPARSE_GRID

    def rmse(lam):
        fit = PriorLeastSquares(B, lo, hi, lam, rest_pull=l1_weights(B, 0.5, z))
        return np.sqrt(np.mean((np.array([fit.step(s, v) for s, v in zip(S, V, strict=True)]) - W) ** 2))

    errs = [rmse(lam) for lam in SPARSE_GRID]
    assert rmse(a.value) < 1.15 * min(errs)
