"""The noise study: its measures (lag, blink amplitude) and the command end to end on the demo rig."""

from __future__ import annotations

import json

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.cli import main
from livecap.cli.noise_study import blink_amplitude, lag_frames, variants


def curves(T=900, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T) / 120.0
    return np.stack([np.sin(2 * np.pi * f * t + p) ** 2 for f, p in zip(rng.uniform(0.2, 1.5, 4),
                                                                       rng.uniform(0, 6, 4), strict=True)], 1)


@settings(max_examples=15, deadline=None)
@given(st.integers(-8, 8))
def test_lag_finds_a_known_delay(shift):
    truth = curves()
    delayed = np.roll(truth, shift, axis=0)
    assert abs(lag_frames(delayed[20:-20], truth[20:-20]) - shift) < 0.05


def test_blink_amplitude_ratio():
    t = np.arange(600)
    bump = np.where(np.abs(t - 300) < 15, 0.5 + 0.5 * np.cos(np.pi * (t - 300) / 15), 0.0)
    truth = np.stack([bump, bump * 0.2], 1)
    assert blink_amplitude(0.8 * truth, truth, ["eyeBlinkLeft", "jawOpen"]) == 0.8 * 1.0 / 1.0
    assert np.isnan(blink_amplitude(truth, truth, ["a", "b"]))


def test_every_registered_mode_and_a_filtered_twin_is_studied():
    names = [n for n, _ in variants(None)]
    assert "lsq" in names and "lsq+1e" in names and "robust" in names and "robust+1e" not in names


def test_noise_study_command_on_demo_rig(tmp_path, demo, capsys):
    rig, layout = demo
    rig.save(tmp_path / "r.npz")
    layout.save(tmp_path / "r.markers.json")
    plot, out = tmp_path / "study.png", tmp_path / "study.json"
    code = main(["noise-study", "--rig", str(tmp_path / "r.npz"), "--seconds", "8", "--modes", "lsq", "robust",
                 "--no-sweep", "--plot", str(plot), "--json", str(out)])
    assert code == 0
    text = capsys.readouterr().out
    assert "selected: noise" in text and "RMSE" in text and "best streaming" in text
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = {r["mode"]: r for r in json.loads(out.read_text())["rows"]}
    lsq, robust = rows["lsq"], rows["robust"]
    assert robust["rmse"] <= 0.5 * lsq["rmse"]  # the RMSE check, on a short take
    assert robust["jitter_ratio"] < 0.2 * lsq["jitter_ratio"]
    assert robust["lag"] <= 1.0 and robust["vertex_mm"] < lsq["vertex_mm"]
    assert robust["blink"] >= 0.9  # the sparse fit with hysteresis keeps blink amplitude
