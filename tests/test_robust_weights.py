"""The robust mode's weight stage: the IMM wired with per-shape noise, against the 1€ stage it replaced."""

import numpy as np
import pytest

from livecap.calibration.profile import calibrate
from livecap.cli.noise_study import lag_frames
from livecap.demo.performance import PerformanceSettings, perform
from livecap.modes.robust import robust_solver, weight_filter, weight_noise
from livecap.offline.metrics import jitter
from livecap.offline.solve import prepare_targets
from solvers.filters import OneEuroFilter
from solvers.tracking import IMMFilter


@pytest.fixture(scope="module")
def take(demo):
    rig, layout = demo
    perf = perform(rig, layout, PerformanceSettings(seconds=8.0, occlusion=0.05, seed=3))
    profile = calibrate(rig, layout, perf.actor_neutral)  # untuned: the default 0.5 mm noise, as generated
    _, S, _, _ = prepare_targets(perf.take, profile)
    return profile, S, perf.take.valid, perf.weights


def test_weight_stage_selection_and_noise(take):
    profile = take[0]
    f = weight_filter(profile, {"rate": 120.0}, gain=0.5)
    assert isinstance(f, IMMFilter)
    norms = np.linalg.norm(profile.basis, axis=0)
    np.testing.assert_allclose(f.r, 0.5**2 * 0.5 / norms**2)
    np.testing.assert_allclose(weight_noise(profile, {"noise_mm": 0.2}, 1.0), 0.04 / norms**2)
    assert isinstance(weight_filter(profile, {"weight_filter": "1e"}), OneEuroFilter)
    with pytest.raises(ValueError, match="weight filter"):
        weight_filter(profile, {"weight_filter": "median"})


def test_imm_stage_is_smoother_than_the_one_euro_at_no_more_lag(take):
    profile, S, valid, truth = take
    out = {}
    for kind in ("imm", "1e"):
        solver = robust_solver(profile, {"rate": 120.0, "weight_filter": kind})
        W = np.array([solver.step(S[t], valid[t]) for t in range(len(S))])
        out[kind] = (jitter(W) / jitter(truth), lag_frames(W, truth))
    assert out["imm"][0] < 0.85 * out["1e"][0]
    assert out["imm"][1] <= max(out["1e"][1], 0.0) + 0.15 and out["imm"][1] <= 1.0


def test_noise_study_tradeoff_lists_both_families(take, demo):
    from livecap.cli.noise_study import tradeoff

    profile, S, valid, truth = take
    rows = tradeoff(profile, S[:600], valid[:600], truth[:600], demo[0].names, 120.0, jitter(truth[:600]))
    imm = [r for r in rows if r["filter"].startswith("imm") and "marginal" not in r["filter"]]
    assert rows[0]["filter"] == "none" and any(r["filter"].startswith("1e") for r in rows) and len(imm) >= 3
    jit = [r["jitter_ratio"] for r in imm]  # a slower 'move' model: smoother (and later) output
    assert all(a > b for a, b in zip(jit, jit[1:], strict=False))


def test_marginal_weight_noise_is_the_least_squares_variance(take):
    """'marginal': the diagonal of sigma^2 (B^T B + ridge)^-1, never below the shape-alone variance."""
    profile = take[0]
    B = profile.basis
    got = weight_noise(profile, {"weight_noise": "marginal", "noise_mm": 0.5, "ridge": 0.1}, 1.0)
    np.testing.assert_allclose(got, 0.25 * np.diag(np.linalg.inv(B.T @ B + 0.1 * np.eye(B.shape[1]))))
    alone = weight_noise(profile, {"noise_mm": 0.5}, 1.0)
    norms2 = np.linalg.norm(B, axis=0) ** 2
    assert np.all(got >= alone * norms2 / (norms2 + 0.1) - 1e-12)  # conditioning only adds variance
