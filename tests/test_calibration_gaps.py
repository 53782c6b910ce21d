"""Gap filling (Curio 2006 §2.1) and the no-NaN guarantee of the offline path."""

import numpy as np

from livecap.calibration.gaps import fill_gaps, gap_runs


def _trajectories(T=240, n=4, noise=0.0, seed=0):
    t = np.arange(T)[:, None, None] / 120.0
    rng = np.random.default_rng(seed)
    freq = rng.uniform(0.3, 1.5, (1, n, 3))
    pos = 10 * np.sin(2 * np.pi * freq * t + rng.uniform(0, 6, (1, n, 3)))
    return pos, pos + rng.normal(0, noise, pos.shape)


def test_gap_runs():
    assert gap_runs(np.array([1, 0, 0, 1, 0, 1, 1, 0], bool)) == [(1, 3), (4, 5), (7, 8)]
    assert gap_runs(np.ones(4, bool)) == []


def test_short_interior_gaps_are_filled_long_and_edge_gaps_stay_missing():
    truth, pos = _trajectories()
    valid = np.ones(pos.shape[:2], bool)
    valid[50:70, 0] = False  # 20 frames: filled
    valid[100:200, 1] = False  # 100 frames: too long
    valid[:10, 2] = False  # leading: nothing to interpolate from
    valid[230:, 3] = False  # trailing
    pos[~valid] = np.nan
    out, ok = fill_gaps(pos, valid, max_gap=30)
    assert np.isfinite(out).all()
    assert ok[50:70, 0].all() and not ok[100:200, 1].any() and not ok[:10, 2].any() and not ok[230:, 3].any()
    assert np.all(out[~ok] == 0.0)
    assert np.abs(out[50:70, 0] - truth[50:70, 0]).max() < 0.05  # smooth motion: a cubic follows it
    np.testing.assert_array_equal(out[valid], pos[valid])  # seen samples untouched


def test_noisy_samples_do_not_make_the_fill_overshoot():
    truth, pos = _trajectories(noise=0.5, seed=1)
    valid = np.ones(pos.shape[:2], bool)
    valid[1:29, :] = False  # one sample before the gap, as in a real take
    valid[120:150, :] = False
    out, ok = fill_gaps(pos, valid, max_gap=30)
    assert ok.all()
    assert np.abs(out[120:150] - truth[120:150]).max() < 3.0  # a quarter second of 10 mm, 1.5 Hz motion
    assert np.abs(out[1:29] - truth[1:29]).max() < 6.0  # an interpolating spline overshoots by centimetres here


def test_zero_max_gap_fills_nothing():
    _, pos = _trajectories()
    valid = np.ones(pos.shape[:2], bool)
    valid[5:8, 0] = False
    out, ok = fill_gaps(pos, valid, 0)
    np.testing.assert_array_equal(ok, valid)


def test_offline_solve_fills_gaps_and_no_nan_reaches_the_solver(demo):
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.demo.performance import PerformanceSettings, perform
    from livecap.offline.solve import prepare_targets, solve_take

    rig, layout = demo
    perf = perform(rig, layout, PerformanceSettings(seconds=3, rate=60, occlusion=0.05, seed=2))
    take = perf.take
    take.positions[~take.valid] = np.nan  # what a careless reader might hand over
    profile = calibrate(rig, layout, estimate_neutral(take, layout.stable, 30))
    filled, targets, _, _ = prepare_targets(take, profile)
    raw, targets0, _, _ = prepare_targets(take, profile, max_gap_seconds=0)
    assert np.isfinite(targets).all() and np.isfinite(targets0).all()
    np.testing.assert_array_equal(raw.valid, take.valid)
    assert filled.valid.sum() > take.valid.sum()
    assert (filled.valid | ~take.valid).all()

    seen = []

    class Recorder:
        def step(self, target, valid):
            seen.append(np.isfinite(target).all())
            return np.zeros(rig.n_shapes)

    solved = solve_take(take, profile, Recorder())
    assert all(seen) and len(seen) == take.n_frames
    assert solved.valid.sum() == filled.valid.sum()


def _performance_tracks(seconds=2.5, noise=0.5):
    """Demo-rig marker tracks in the head frame (no head motion), clean and with sensor noise."""
    from livecap.demo.face import demo_rig
    from livecap.demo.performance import PerformanceSettings, perform

    rig, layout = demo_rig(0)
    kw = dict(seconds=seconds, occlusion=0.0, head_degrees=0, head_mm=0, stable_dropout=0, seed=3)
    clean = perform(rig, layout, PerformanceSettings(noise_mm=0.0, **kw)).take.positions[:, ::6]
    noisy = perform(rig, layout, PerformanceSettings(noise_mm=noise, **kw)).take.positions[:, ::6]
    return clean, noisy


def test_banded_fill_is_as_accurate_as_the_per_gap_spline_on_gaps_of_1_to_60_frames():
    from livecap.calibration.gaps_spline import fill_gaps_per_gap

    clean, noisy = _performance_tracks()
    T, n = clean.shape[:2]
    rng = np.random.default_rng(4)
    for length in (1, 3, 8, 20, 40, 60):
        valid = np.ones((T, n), bool)
        for j in range(n):
            a = rng.integers(70, T - 70 - length)
            valid[a:a + length, j] = False
        pos = np.where(valid[..., None], noisy, np.nan)
        new, ok_new = fill_gaps(pos, valid, 60)
        ref, ok_ref = fill_gaps_per_gap(pos, valid, 60)
        np.testing.assert_array_equal(ok_new, ok_ref)
        gap = ~valid
        err_new = np.sqrt(np.mean(np.sum((new[gap] - clean[gap]) ** 2, -1)))
        err_ref = np.sqrt(np.mean(np.sum((ref[gap] - clean[gap]) ** 2, -1)))
        assert err_new <= 1.05 * err_ref, (length, err_new, err_ref)


def test_straight_tracks_are_filled_exactly_and_gaps_next_to_each_other_are_all_filled():
    T, n = 200, 3
    t = np.arange(T, dtype=float)[:, None, None]
    pos = 2.0 + 0.3 * t * np.array([1.0, -2.0, 0.5]) + np.arange(n)[None, :, None]
    valid = np.ones((T, n), bool)
    valid[10:12, 0] = valid[13:40, 0] = valid[41:42, 0] = False  # gaps one sample apart
    valid[1:61, 1] = False  # one seen sample before a 60-frame gap
    valid[190:199, 2] = False
    out, ok = fill_gaps(np.where(valid[..., None], pos, 0.0), valid, 60)
    assert ok.all()
    np.testing.assert_allclose(out, pos, atol=1e-6)  # a line has no second difference: nothing to smooth
