"""benchmarks/kalman_speed.py at a toy size: each part runs and reports what the docs' tables read."""

from __future__ import annotations

import numpy as np

from benchmarks import kalman_speed
from benchmarks.kalman_step import WARMUP, synthetic_case


def test_streamed_sets_kalman_beside_robust_and_returns_its_weights():
    profile, targets, valid, options = synthetic_case(12, 8, WARMUP + 20)
    res, W = kalman_speed.streamed(profile, targets, valid, options)
    assert W.shape == (WARMUP + 20, 8) and np.isfinite(W).all()
    for label in ("robust", "kalman", "kalman, no strength trial"):
        assert 0 < res[label]["p50"] <= res[label]["p99"] and res[label]["wall"]["p50"] > 0
    assert res["kalman / robust"]["p50"] == res["kalman"]["p50"] / res["robust"]["p50"]


def test_a_paced_stream_hands_each_frame_over_at_its_time():
    """``--only paced``: frame i is stepped no sooner than i / rate after the first (as a live source delivers it),
    with the same weights as unpaced."""
    import time

    profile, targets, valid, options = synthetic_case(12, 8, 12)
    handed = []

    class Clocked:
        def __init__(self, solver):
            self.solver = solver

        def step(self, target, seen):
            handed.append(time.perf_counter())
            return self.solver.step(target, seen)

    from benchmarks.kalman_step import _build

    W, cpu, wall = kalman_speed._stream(Clocked(_build(profile, options, "robust")), targets, valid, pace_hz=100.0)
    late = np.array(handed) - handed[0] - np.arange(12) / 100.0
    assert late.min() > -1e-3 and cpu.shape == wall.shape == (12,)
    W0, _, _ = kalman_speed._stream(_build(profile, options, "robust"), targets, valid)
    np.testing.assert_array_equal(W, W0)


def test_marker_space_primitives_are_timed():
    out = kalman_speed.marker_space(free=20, rows=12, m=40, reps=2)
    assert set(out["median_us"]) == {"weight-space Cholesky of H_FF", "marker-space factor, fresh",
                                     "marker-space solve, kept factor", "gradient J'Jx, all weights",
                                     "marker-space refactor, 66 columns changed (dsyrk + dpotrf)"}
    assert all(v > 0 for v in out["median_us"].values())


def test_offline_parts_split_kalmans_cpu_by_stage():
    from benchmarks.synthetic import synthetic_profile, synthetic_stream
    from livecap.core.take import Take

    profile = synthetic_profile(12, 8)
    S, V, _ = synthetic_stream(profile, 90)
    take = Take(list(profile.labels), np.asarray(S, float) + profile.source_neutral, V, 60.0)
    out = kalman_speed.offline_parts(take, profile)
    assert set(out) == {"total", "rest", "calls", *kalman_speed.PARTS}
    assert 0 < out["marker smoother"] < out["total"] and out["fit"] > 0 and out["strength in closed form"] > 0
    # per pose pass: the stages run once a pass are told apart, and the stages and the rest make the whole
    from livecap.modes.marker_kalman import POSE_PASSES

    assert len(out["calls"]["marker smoother"]) == len(out["calls"]["fit"]) == POSE_PASSES
    assert sum(out["calls"]["fit"]) == out["fit"]
    assert abs(sum(out[k] for k in kalman_speed.PARTS) + out["rest"] - out["total"]) < 1e-9
    assert out["held-out strength trials"] == 0  # a whole take runs no trial QP (issue 39 item 2)


def test_the_frame_profile_splits_a_step_into_its_parts():
    from tests.test_prior_support import _tight_prior_take

    p, _, X = _tight_prior_take(T=200)
    valid = np.ones((len(X), X.shape[1]), bool)
    valid[100:, 3] = False  # a new visibility pattern half way
    out = kalman_speed.frame_profile(p, X.reshape(len(X), -1), valid, {"rate": 60.0})
    parts = out["parts"]
    assert parts["marker filter"]["mean"] > 0 and parts["weight IMM"]["mean"] > 0
    assert out["frames_with"]["prior check start"]["all"] > 0 and out["frames_with"]["prior swap"]["all"] > 0
    assert out["frames_with"]["next pattern's workspace"]["all"] > 0
    assert parts["prior check (frames, start, swap)"]["top_mean"] > 0 and out["top_frames"] == 2  # 1 % of 150
    # the frame after each swap, and the fit's restart on the new pattern (and on the first frames after a swap)
    assert out["frames_with"]["after a prior swap"]["all"] == out["frames_with"]["prior swap"]["all"]
    assert 0 < out["frames_with"]["fit restart"]["all"] < 0.1
    assert out["fit_p50_us_on"]["fit restart"] > 0 and out["p99_without_check_frames"] > 0
