"""Marker-space Kalman filter / RTS smoother, held-out prior strength, animation prior (issue 15)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.calibration.animation_prior import AnimationPrior
from livecap.cli import main
from solvers.marker_kalman import StreamingMarkerKalman, bridged, smooth_take
from solvers.pose_refine import refit_pose
from solvers.prior_strength import HeldOutStrength
from solvers.rigid import kabsch
from tests.test_curves_take import short_csv  # noqa: F401 - fixture


def _walk(T: int, n: int, noise: float, seed: int):
    rng = np.random.default_rng(seed)
    acc = rng.normal(0, 0.02, (T, n, 3))
    truth = np.cumsum(np.cumsum(acc, 0), 0)
    return truth, truth + rng.normal(0, noise, truth.shape)


@settings(max_examples=10, deadline=None)
@given(x0=st.floats(-50, 50), v=st.floats(-2, 2))
def test_rts_reproduces_constant_velocity_exactly(x0, v):
    t = np.arange(40, dtype=float)
    targets = np.broadcast_to((x0 + v * t)[:, None, None], (40, 2, 3)).copy()
    out, ok, _ = smooth_take(targets, np.ones((40, 2), bool))
    assert np.allclose(out, targets, atol=1e-6 * (1 + abs(x0))) and ok.all()


def test_smoother_and_filter_cut_noise_and_likelihood_finds_it():
    truth, noisy = _walk(400, 4, 0.5, 1)
    valid = np.ones((400, 4), bool)
    valid[100:110, 0] = False
    out, ok, chosen = smooth_take(noisy, valid)
    assert chosen["noise_mm"] == pytest.approx(0.5, abs=0.21)
    raw_err = np.sqrt(np.mean((noisy - truth) ** 2))
    assert np.sqrt(np.mean((out - truth)[ok] ** 2)) < 0.5 * raw_err
    f = StreamingMarkerKalman(4, lag=1)
    streamed = np.array([f.step(noisy[t], valid[t])[0] for t in range(400)])
    assert np.sqrt(np.mean((streamed[101:] - truth[100:-1]) ** 2)) < 0.8 * raw_err  # one frame late


def test_bridged_fills_short_gaps_only():
    v = np.ones((30, 1), bool)
    v[5:8] = False
    v[12:25] = False
    b = bridged(v, 5)
    assert b[5:8].all() and not b[12:25].any()


def test_held_out_strength_prefers_stronger_prior_for_noisier_markers():
    rng = np.random.default_rng(0)
    B = rng.normal(0, 1, (30, 6)) @ np.diag([1, 1, 1, 0.3, 0.1, 0.05])
    W = np.clip(rng.normal(0.3, 0.15, (400, 6)), 0, 1)
    picks = []
    for noise in (0.01, 1.0):
        sel = HeldOutStrength(B, np.zeros(6), np.ones(6), np.full(6, 0.3), np.eye(6) / 0.15 ** 2,
                              np.logspace(-4, 1, 6))
        for w in W:
            sel.observe((B @ w).reshape(10, 3) + rng.normal(0, noise, (10, 3)), np.ones(10, bool))
        picks.append(sel.best)
    assert picks[0] < picks[1]


def test_prior_build_cli_and_kalman_solve(tmp_path, short_csv, capsys):  # noqa: F811
    out = tmp_path / "p.npz"
    assert main(["prior", "build", str(short_csv), "--rig", "recordings/demo_rig.npz", "--out", str(out)]) == 0
    p = AnimationPrior.load(out)
    assert p.cov.shape == (43, 43) and np.all(np.linalg.eigvalsh(p.cov) > 0) and p.frames == 328
    assert main(["generate", "--curves", str(short_csv), "--seconds", "2", "--out", str(tmp_path)]) == 0
    take, neutral = tmp_path / f"{short_csv.stem}.c3d", tmp_path / f"{short_csv.stem}_neutral.c3d"
    assert main(["calibrate", str(neutral), "--rig", "recordings/demo_rig.npz", "--out", str(tmp_path / "a.npz")]) == 0
    assert main(["solve", str(take), "--rig", "recordings/demo_rig.npz", "--mode", "kalman", "--prior", str(out),
                 "--profile", str(tmp_path / "a.npz"), "--out", str(tmp_path / "w.csv")]) == 0
    assert len((tmp_path / "w.csv").read_text().splitlines()) == 121


def _blink_take(noise: float, seed: int):
    """Markers still for 2 s, one fast 3 mm pulse (8 frames, a blink at 60 Hz), still again."""
    T = 300
    pulse = np.zeros(T)
    pulse[150:159] = 3.0 * np.sin(np.linspace(0, np.pi, 9)) ** 2
    truth = np.zeros((T, 4, 3))
    truth[:, :, 1] = pulse[:, None]
    return truth, truth + np.random.default_rng(seed).normal(0, noise, truth.shape), pulse


def test_local_process_noise_keeps_a_blink_and_smooths_the_still_face():
    truth, noisy, pulse = _blink_take(0.3, 2)
    out, _, _ = smooth_take(noisy, np.ones(noisy.shape[:2], bool))
    peak = out[150:159, :, 1].max(0).mean()
    assert peak > 0.8 * pulse.max()  # one q for the take (before issue 15's fix) kept 0.07 of it
    still = np.concatenate([out[:120], out[190:]]) - np.concatenate([truth[:120], truth[190:]])
    assert np.sqrt(np.mean(still ** 2)) < 0.25 * 0.3


def test_pose_refit_from_the_smoothed_markers_keeps_the_raw_noise_out_of_the_pose():
    rng = np.random.default_rng(3)
    neutral = rng.normal(0, 30, (12, 3))
    stable = np.arange(12) < 6
    basis = np.zeros((36, 2))
    angle = 0.02
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    moved = (neutral @ R.T + [0.5, -0.3, 0.2] - neutral)[None].repeat(50, 0)  # a pose error, no expression
    noise = rng.normal(0, 0.5, moved.shape)
    valid = np.ones((50, 12), bool)
    W = np.zeros((50, 2))
    fixed = refit_pose(moved + noise, valid, W, neutral, stable, basis, pose_from=moved)
    raw = refit_pose(moved + noise, valid, W, neutral, stable, basis)
    R0, t0 = kabsch(neutral + moved[0], neutral)  # the true correction
    expected = (neutral + moved + noise) @ R0.T + t0 - neutral
    assert np.allclose(fixed, expected, atol=1e-6)  # from noise-free smoothed markers: the true correction
    # fitted on the raw stable markers, each frame's correction follows their noise: a rigid jitter
    assert np.sqrt(np.mean((raw - expected)[:, ~stable] ** 2)) > 0.15


def test_weight_motion_stage_follows_a_ramp_without_lag_and_cuts_noise():
    from livecap.modes.marker_kalman import WeightMotion

    rate, T = 60.0, 240
    truth = np.clip((np.arange(T) - 60) / 60.0, 0, 1)[:, None] * np.ones((1, 3))  # 1 s ramps
    noisy = truth + np.random.default_rng(4).normal(0, 0.02, truth.shape)
    out = WeightMotion(rate, 0.5, 80.0, 0.8).imm(0.5, np.full(3, 25.0)).filter(noisy)
    lag = min(range(0, 5), key=lambda s: np.mean((out[s:] - truth[:T - s]) ** 2))
    assert lag <= 1
    assert np.mean(np.abs(np.diff(out, 2, axis=0))) < 0.3 * np.mean(np.abs(np.diff(noisy, 2, axis=0)))


def test_streaming_lambda_bank_equals_the_full_r_by_q_bank():
    """The streaming filter runs one bank over lambda = q / r and gets every r's likelihood from three
    sums; a bank of every allowed (r, q = lambda r) pair, its velocity prior scaled by r (the same
    filters), with the likelihood per coordinate, must give the same markers and noise."""
    from solvers.marker_kalman import _Bank, _choose

    truth, noisy = _walk(300, 5, 0.3, 6)
    valid = np.random.default_rng(7).random((300, 5)) > 0.1
    valid[40:60, 2] = False
    valid[:30, 4] = False  # a late first sighting
    f = StreamingMarkerKalman(5, lag=0)
    r_grid = np.asarray(f.s.r_grid)
    pairs = [(r, lam) for i, r in enumerate(r_grid) for lam in f.lam[np.isfinite(f.excluded[i, 0])]]
    r, q = np.array(pairs).T
    r, q = r.copy(), q * r
    bank = _Bank(r, q, 5, p11_start=f.p11_start * r[:, None])
    ll = np.zeros((len(r), 5, 3))
    sightings = np.zeros(5, int)
    for t in range(300):
        out, _ = f.step(noisy[t], valid[t])
        if t:
            bank.predict()
        ll = f.decay * ll + np.where((sightings >= 2)[:, None], bank.update(noisy[t], valid[t]), 0.0)
        sightings += valid[t]
        ri, pick = _choose(ll, 5, len(r_grid))
        assert f.noise_mm == pytest.approx(np.sqrt(r_grid[ri]))
        np.testing.assert_allclose(out, bank.x[pick, np.arange(5)], atol=1e-9)


def test_streaming_pose_refit_is_the_batch_refit_of_one_frame_and_carries_part_of_it():
    from solvers.pose_refine import StreamingPoseRefit

    rng = np.random.default_rng(8)
    neutral = rng.normal(0, 30, (12, 3))
    stable = np.arange(12) < 5
    basis = rng.normal(0, 1, (36, 3))
    x = rng.normal(0, 0.5, (12, 3))
    valid = np.ones(12, bool)
    valid[[1, 9]] = False
    w = np.array([0.2, 0.5, 0.1])
    pose = StreamingPoseRefit(neutral, stable, basis)
    np.testing.assert_allclose(pose.apply(x, valid), np.where(valid[:, None], x, 0.0), atol=1e-12)  # the identity
    out = pose.refit(x, valid, w)
    np.testing.assert_allclose(out, refit_pose(x[None], valid[None], w[None], neutral, stable, basis)[0], atol=1e-9)
    half = pose.apply(x, valid, 0.5)
    np.testing.assert_allclose(half[valid], 0.5 * (x + out)[valid], atol=1e-12)
    valid[:4] = False  # one stable marker left: the last correction is kept
    np.testing.assert_allclose(pose.refit(x, valid, w)[valid], out[valid], atol=1e-12)

