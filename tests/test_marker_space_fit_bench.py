"""benchmarks/marker_space_fit.py on a small rig that takes the marker-space path (12 markers, 80 shapes)."""

from __future__ import annotations

import numpy as np

from benchmarks import marker_space_fit as msf


def test_record_replay_and_stream(tmp_path, monkeypatch):
    monkeypatch.setattr(msf, "WARMUP", 5)
    path = str(tmp_path / "ms.npz")
    rec = msf.record(path, frames=30, size=(12, 80))
    assert rec["qps"] > 1 and rec["calls"] > 30  # the fit and the trials took the marker-space path
    out = msf.replay(path)
    X = out.pop("_X")
    z = np.load(path)
    solved = ~z["begin"].astype(bool)
    assert np.isfinite(X[solved]).all() and np.isnan(X[~solved]).all()
    assert out["fit passes (solves) mean"] > 0 and out["fit + trial"]["p99"] > 0
    s = msf.stream(frames=30, size=(12, 80))
    assert s.pop("_W").shape == (30, 80) and 0 < s["rmse"] < 1 and s["p99"] >= s["p50"] > 0
