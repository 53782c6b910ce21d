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


def test_marker_space_primitives_are_timed():
    out = kalman_speed.marker_space(free=20, rows=12, m=40, reps=2)
    assert set(out["median_us"]) == {"weight-space Cholesky of H_FF", "marker-space factor, fresh",
                                     "marker-space solve, kept factor", "gradient J'Jx, all weights"}
    assert all(v > 0 for v in out["median_us"].values())
