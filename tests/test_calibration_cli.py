"""``livecap calibrate`` and ``livecap calibration-report`` as a user runs them (real subprocess, real files)."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from livecap.calibration.profile import Profile

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"


def livecap(*args):
    return subprocess.run([sys.executable, "-m", "livecap", *args], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def short_take(tmp_path_factory, demo):
    """A 4.5 s take at 30 Hz of the bundled demo actor (same rig and actor seed), with ground truth."""
    from livecap.demo import truth_path
    from livecap.demo.performance import PerformanceSettings, perform
    from transport.takefile import write_take

    rig, layout = demo
    out = tmp_path_factory.mktemp("take") / "short.c3d"
    perf = perform(rig, layout, PerformanceSettings(seconds=4.5, rate=30, seed=9))
    write_take(perf.take, out)
    perf.save_truth(truth_path(out))
    return out, perf


def test_calibrate_writes_a_profile_that_solve_uses(short_take, tmp_path):
    prof = tmp_path / "actor.npz"
    r = livecap("calibrate", str(RECORDINGS / "demo_neutral.c3d"), "--rig", str(RECORDINGS / "demo_rig.npz"),
                "--out", str(prof), "--max-gap", "0.1")
    assert r.returncode == 0, r.stderr
    assert "warp      rbf" in r.stdout and prof.exists()
    p = Profile.load(prof)
    assert p.settings["warp"] == "rbf" and p.settings["max_gap_seconds"] == 0.1
    assert p.warp is not None and p.marker_rig is not None and p.basis.shape == (180, 43)
    r = livecap("solve", str(short_take[0]), "--rig", str(RECORDINGS / "demo_rig.npz"), "--profile", str(prof),
                "--out", str(tmp_path / "w.csv"))
    assert r.returncode == 0, r.stderr
    W = np.loadtxt(tmp_path / "w.csv", delimiter=",", skiprows=1)
    rmse = np.sqrt(np.mean((W[:, 2:] - short_take[1].weights) ** 2))
    assert rmse < 0.4


def test_calibrate_similarity_option_and_bad_input(tmp_path):
    r = livecap("calibrate", str(RECORDINGS / "demo_neutral.c3d"), "--rig", str(RECORDINGS / "demo_rig.npz"),
                "--out", str(tmp_path / "s.npz"), "--warp", "similarity", "--seconds", "0.5")
    assert r.returncode == 0, r.stderr
    assert Profile.load(tmp_path / "s.npz").settings["neutral_frames"] == 60
    bad = tmp_path / "broken.c3d"
    bad.write_bytes(b"not a c3d")
    r = livecap("calibrate", str(bad), "--rig", str(RECORDINGS / "demo_rig.npz"), "--out", str(tmp_path / "x.npz"))
    assert r.returncode == 1 and "broken.c3d" in r.stderr and "Traceback" not in r.stderr


def test_calibration_report_shows_the_calibrated_pipeline_better(short_take, tmp_path):
    r = livecap("calibration-report", str(short_take[0]), "--rig", str(RECORDINGS / "demo_rig.npz"),
                "--neutral", str(RECORDINGS / "demo_neutral.c3d"), "--stride", "2",
                "--per-frame", str(tmp_path / "pf.csv"))
    assert r.returncode == 0, r.stderr
    data = np.loadtxt(tmp_path / "pf.csv", delimiter=",", skiprows=2)
    header = (tmp_path / "pf.csv").read_text().splitlines()[0].split(",")
    n_variants = sum(h.startswith("weight_err_") for h in header)
    assert n_variants >= 4 and data.shape == (68, 2 + 2 * n_variants)

    def rmse(i):
        return np.sqrt(np.mean(data[:, header.index(f"weight_err_{i}")] ** 2))

    cal, uncal = rmse(0), rmse(n_variants - 1)  # variant 0 is calibrated, the last uncalibrated
    assert cal < 0.6 * uncal, r.stdout
    assert f"{cal:6.4f}" in r.stdout  # the printed RMSE is the per-frame errors'
    assert "rotation (deg)" in r.stdout and "translation mm" in r.stdout
