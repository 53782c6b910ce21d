"""The movement mode's noise-robust offline solve (livecap/modes/robust_movement.py) against plain Seol."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from livecap.calibration.profile import calibrate, estimate_neutral
from livecap.cli.noise_study import blink_amplitude
from livecap.demo.performance import PerformanceSettings, perform
from livecap.modes.movement import build_movement
from livecap.modes.robust_movement import RobustMovement, smoother_beta
from livecap.offline.metrics import jitter, weight_rmse
from livecap.offline.solve import prepare_targets
from solvers.movement import Edit, MovementMatching
from solvers.prior import PCAPrior
from solvers.regularisation import estimate_noise
from solvers.trend import TOL as TREND_TOL


@pytest.fixture(scope="module")
def take(demo):
    rig, layout = demo
    s = PerformanceSettings(seconds=8.0, noise_mm=0.5, occlusion=0.05, seed=3)
    perf = perform(rig, layout, s)
    neutral = estimate_neutral(perf.take, layout.stable, int(s.neutral_start * perf.take.rate))
    profile = calibrate(rig, layout, neutral)
    _, targets, _, _ = prepare_targets(perf.take, profile)
    profile.settings["robust"] = {"noise_mm": estimate_noise(targets, perf.take.valid)}  # what tune_profile stores
    return profile, targets, perf.take.valid, perf.weights, rig.names


def test_smoother_beta_is_the_noise_variance_ratio():
    assert smoother_beta(4) == pytest.approx(0.3729, abs=1e-4)
    # more smoothing leaves relatively less velocity noise
    assert smoother_beta(2) > smoother_beta(4) > smoother_beta(8) > 0


def test_robust_beats_plain_jitter_and_keeps_blinks(take):
    profile, targets, valid, truth, names = take
    robust = build_movement(profile, {})
    plain = build_movement(profile, {"robust": False})
    assert isinstance(robust, RobustMovement) and isinstance(plain, MovementMatching)
    Wr, Wp = robust.solve(targets, valid), plain.solve(targets, valid)
    tj = jitter(truth)
    jr, jp = jitter(Wr) / tj, jitter(Wp) / tj
    br, bp = blink_amplitude(Wr, truth, names), blink_amplitude(Wp, truth, names)
    assert np.isfinite(br) and np.isfinite(bp)  # the take has blinks
    assert jr < 0.01 * jp  # measured on this 8 s take: robust 2.4 x truth, plain 1023 x
    assert br >= 0.85 and br > bp + 0.3  # measured 0.92 vs 0.29: the shapes prior shrinks blinks
    assert weight_rmse(Wr, truth) < weight_rmse(Wp, truth)
    assert Wr.min() >= profile.lower.min() - 1e-9 and Wr.max() <= profile.upper.max() + 1e-9
    assert np.allclose(Wr[0], 0) and np.allclose(Wr[-1], 0)  # neutral boundaries kept after smoothing


def test_plain_option_is_the_old_solve(take):
    profile, targets, valid, _, _ = take
    old = MovementMatching(profile.basis, profile.lower, profile.upper, alpha=1.0,
                           prior=PCAPrior.from_shapes(profile.basis, 1e-6), beta=0.1, limits="clip")
    assert np.array_equal(build_movement(profile, {"robust": False}).solve(targets, valid), old.solve(targets, valid))
    untuned = dataclasses.replace(profile, settings={})  # no noise estimate: plain Seol
    assert isinstance(build_movement(untuned, {}), MovementMatching)
    assert not isinstance(build_movement(profile, {"stream": True}), RobustMovement)


def test_edits_keep_working(take):
    profile, targets, valid, _, names = take
    solver = build_movement(profile, {})
    W = solver.solve(targets, valid)
    j = names.index("jawOpen")
    value = 0.9 if W[400, j] < 0.45 else 0.0  # a change of at least 0.45 at the edit frame
    E = solver.edit(W, [Edit(400, {j: value}, (380, 420))], targets, valid)
    assert abs(E[400, j] - value) < 1e-9
    assert np.array_equal(E[:381], W[:381]) and np.array_equal(E[420:], W[420:])
    assert np.abs(E[390:400, j] - W[390:400, j]).max() > 0.05


def test_reweighting_lifts_blinks(take):
    profile, targets, valid, truth, names = take
    W0 = build_movement(profile, {}).solve(targets, valid)
    W1 = build_movement(profile, {"reweight": 1}).solve(targets, valid)
    assert blink_amplitude(W1, truth, names) > blink_amplitude(W0, truth, names) + 0.02


def test_an_edit_keeps_resting_shapes_at_rest(take):
    """The range is re-solved under the solve's own L1 term: shapes at rest around the edit stay at 0."""
    profile, targets, valid, _, names = take
    solver = build_movement(profile, {})
    W = solver.solve(targets, valid)
    j = names.index("jawOpen")
    E = solver.edit(W, [Edit(400, {j: 0.9 if W[400, j] < 0.45 else 0.0}, (380, 420))], targets, valid)
    others = np.arange(W.shape[1]) != j
    resting = (W[381:420][:, others] <= TREND_TOL).all(0)  # at rest (to the trend filter's tolerance) before the edit
    assert resting.any()
    moved = np.abs(E[381:420][:, others][:, resting])
    assert moved.max() < 0.1 and moved.mean() < 0.01  # without the L1 term: a shape reaches 1, mean ~0.08


def test_trend_filter_takes_the_jitter_the_l1_solve_leaves(take):
    """The l1 trend filter on the weight curves (solvers/trend.py) is what brings jitter near truth's."""
    profile, targets, valid, truth, names = take
    W = build_movement(profile, {}).solve(targets, valid)
    W0 = build_movement(profile, {"trend": 0}).solve(targets, valid)
    tj = jitter(truth)
    assert jitter(W) / tj < 4 and jitter(W0) / tj > 10 * jitter(W) / tj  # measured 2.4 x vs 99 x
    assert blink_amplitude(W, truth, names) > blink_amplitude(W0, truth, names) - 0.02


def test_an_edited_range_is_as_smooth_as_the_solve(take):
    """The re-solved frames are trend-filtered with the key and range ends fixed, like the solve: a
    range re-solved without a change is as smooth as before, not the raw L1 solve's jitter."""
    profile, targets, valid, _, _ = take
    solver = build_movement(profile, {})
    W = solver.solve(targets, valid)
    edits = [Edit(400, {}, (340, 460))]
    E = solver.edit(W, edits, targets, valid)
    raw = solver.inner.edit(W, edits, solver.smooth(targets, valid), valid, linear=solver.mu)
    inside = slice(341, 460)
    assert np.array_equal(E[400], W[400]) and np.array_equal(E[:341], W[:341]) and np.array_equal(E[460:], W[460:])
    assert jitter(E[inside]) < 0.2 * jitter(raw[inside])  # measured 0.08 x
    assert jitter(E[inside]) < 1.5 * jitter(W[inside])  # measured 1.0 x


def test_misfit_weights_count_markers_the_rig_cannot_follow_less_only_under_measured_mismatch():
    """Issue 35: under model mismatch the position term weights a marker by min(1, (sigma / sigma_i)^2)."""
    from types import SimpleNamespace

    from livecap.modes.movement import misfit_weights

    robust = {"noise_mm": 1.0, "marker_noise_mm": [0.5, 1.0, 2.0], "jitter_mm": 0.01, "residual_mm": 1.0}
    prof = SimpleNamespace(labels=["a", "b", "c"], basis=np.zeros((9, 2)), settings={"robust": robust})
    assert misfit_weights(prof) == {"a": 1.0, "b": 1.0, "c": pytest.approx(0.25)}
    same_rig = {**robust, "jitter_mm": 0.9}  # jitter ~ residual: white noise, the rig fits
    assert misfit_weights(SimpleNamespace(labels=prof.labels, basis=prof.basis, settings={"robust": same_rig})) is None


def test_streamed_step_is_causal_and_smooth(take):
    """Issues 35 / 41: ``step`` (what ``livecap run --mode movement`` streams) was the plain sliding window on the
    raw markers, i.e. the per-frame least-squares fit (jitter hundreds of times the truth's); now the marker filter,
    the movement step and the IMM keep it near the offline solve, causal with one frame of latency."""
    from livecap.offline.real_eval import streamed

    profile, targets, valid, truth, _ = take
    solver = build_movement(profile, {})
    offline = solver.solve(targets, valid)
    solver.reset()
    live = streamed(solver, targets, valid)
    solver.inner.reset()
    window = streamed(solver.inner, targets, valid)  # the plain sliding window (main's streamed movement)
    tj = jitter(truth)  # measured on this 8 s take: live 5.0 x truth, window 5818 x, offline 2.4 x
    assert jitter(live) / tj < 0.05 * jitter(window) / tj
    assert jitter(live) / tj < 10.0
    assert weight_rmse(live, truth) < 1.25 * weight_rmse(offline, truth)  # 0.057 vs 0.055 (window 0.35)
    assert weight_rmse(live, truth) < 0.6 * weight_rmse(window, truth)
    assert live.min() >= profile.lower.min() - 1e-9 and live.max() <= profile.upper.max() + 1e-9
    assert solver.latency_frames == 1  # the marker filter's fixed lag; the live pipeline pairs frames by it
    solver.reset()  # reset forgets the stream: the same weights again (the last frame is the helper's padding)
    assert np.allclose(streamed(solver, targets[:120], valid[:120])[:119], live[:119])


def test_streamed_beta_follows_the_jitter_share_of_the_noise():
    """White noise (jitter ~ calibration's noise): live_beta; model mismatch (the noise is the rig's misfit, the
    AnimFace takes' 0.005 mm jitter against 1.39 mm): the offline beta, so the movement term leads; never below it."""
    from types import SimpleNamespace

    from livecap.modes.movement import MovementSettings, streamed_beta

    s = MovementSettings(beta=0.373, live_beta=5.0)

    def beta(**tuned):
        return streamed_beta(SimpleNamespace(settings={"robust": tuned}), s)

    assert beta(noise_mm=0.5, jitter_mm=0.5) == pytest.approx(5.0)
    assert beta(noise_mm=0.51, jitter_mm=0.498) == pytest.approx(5.0 * (0.498 / 0.51) ** 2)
    assert beta(noise_mm=1.386, jitter_mm=0.005) == pytest.approx(0.373)
    assert beta(noise_mm=0.5) == pytest.approx(5.0)  # profiles tuned before the jitter was stored
