"""Issue 35.2: the noise the solvers use includes what the rig cannot explain, smoothed data cannot drive it to 0,
--noise-mm overrides it, and calibration warns when jitter and fit residual disagree."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.calibration.profile import Profile
from livecap.cli import main
from livecap.modes.robust import tune_profile
from solvers.regularisation import estimate_noise, fit_residual

REC = Path(__file__).resolve().parents[1] / "recordings"
RIG = str(REC / "demo_rig.npz")


@pytest.fixture(scope="module")
def profile_path(demo_profile_path):
    return demo_profile_path


@settings(max_examples=10, deadline=None)
@given(sigma=st.floats(0.05, 2.0), seed=st.integers(0, 2**16))
def test_fit_residual_reads_white_noise_as_its_sigma(sigma, seed):
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(90, 20))
    W = rng.uniform(0, 1, size=(400, 20))
    S = (W @ B.T + sigma * rng.normal(size=(400, 90))).reshape(400, 30, 3)
    r = fit_residual(B, S, np.ones((400, 30), bool), ridge=1e-6)
    assert np.all(np.abs(r / sigma - 1) < 0.2)


def _smoothed_mismatch(profile: Profile, amplitude: float, seed: int = 0):
    """A still-ish actor whose markers move in directions the rig cannot follow, smoothed as a capture pipeline
    does: frame-to-frame second differences ~0, fit residual ~amplitude."""
    rng = np.random.default_rng(seed)
    T, n = 600, len(profile.labels)
    t = np.arange(T) / 120.0
    phase = rng.uniform(0, 2 * np.pi, size=(n, 3))
    S = amplitude * np.sin(2 * np.pi * 0.4 * t[:, None, None] + phase) + 0.01 * rng.normal(size=(T, n, 3))
    kernel = np.ones(15) / 15
    S = np.apply_along_axis(lambda x: np.convolve(x, kernel, mode="same"), 0, S)
    return S, np.ones((T, n), bool)


def test_smoothed_data_cannot_drive_the_noise_to_zero_and_calibration_warns(profile_path, caplog):
    profile = Profile.load(profile_path)
    S, valid = _smoothed_mismatch(profile, 1.5)
    assert estimate_noise(S, valid) < 0.02  # what the solvers used before
    with caplog.at_level(logging.WARNING, logger="livecap.modes.robust"):
        tuned = tune_profile(profile, S, valid, 120.0)
    assert tuned["jitter_mm"] < 0.02 and tuned["noise_mm"] > 0.5 and tuned["noise_source"] == "residual"
    assert len(tuned["marker_noise_mm"]) == len(profile.labels)
    assert any("jitter" in r.getMessage() and "--noise-mm" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="livecap.modes.robust"):
        tuned = tune_profile(profile, S, valid, 120.0, noise_mm=0.3)
    assert tuned["noise_mm"] == 0.3 and tuned["noise_source"] == "given" and not caplog.records


def test_white_noise_keeps_its_estimate(profile_path):
    """The demo neutral (0.5 mm white noise, the rig's own shapes): noise stays ~0.5, no disagreement."""
    r = Profile.load(profile_path).settings["robust"]
    assert 0.45 < r["jitter_mm"] < 0.55 and r["noise_mm"] < 1.1 * r["jitter_mm"]


def test_noise_mm_overrides_calibration_and_solve(profile_path, tmp_path):
    out = tmp_path / "given.npz"
    assert main(["calibrate", str(REC / "demo_neutral.c3d"), "--rig", RIG, "--out", str(out),
                 "--noise-mm", "0.3"]) == 0
    assert Profile.load(out).settings["robust"]["noise_mm"] == 0.3
    take = tmp_path / "short.c3d"
    from transport.takefile import read_take, write_take

    write_take(read_take(REC / "demo_take.c3d").slice(0, 240), take)
    csv = {}
    for extra in ([], ["--noise-mm", "2.0"]):
        csv[len(extra)] = tmp_path / f"w{len(extra)}.csv"
        assert main(["solve", str(take), "--rig", RIG, "--profile", str(profile_path), "--mode", "robust",
                     "--out", str(csv[len(extra)]), *extra]) == 0
    assert csv[0].read_text() != csv[2].read_text()
