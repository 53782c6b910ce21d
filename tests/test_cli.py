"""The CLI as a user runs it: a real subprocess on real files."""

import subprocess
import sys

import numpy as np
import pytest

from transport.weights_csv import read_weights_csv


def livecap(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "livecap", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=600)


@pytest.fixture(scope="module")
def short_demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec")
    r = livecap("generate", "--out", str(out), "--seconds", "4")
    assert r.returncode == 0, r.stderr
    return out


def test_solve_writes_one_row_per_frame(short_demo, tmp_path):
    r = livecap("solve", str(short_demo / "demo_take.c3d"), "--rig", str(short_demo / "demo_rig.npz"),
                "--out", str(tmp_path / "w.csv"))
    assert r.returncode == 0, r.stderr
    names, W, times = read_weights_csv(tmp_path / "w.csv")
    assert len(W) == 480 and len(names) == 43 and "jawOpen" in names
    assert np.all(W >= 0) and np.all(W <= 1)
    assert np.isclose(times[1] - times[0], 1 / 120, atol=1e-6)


def test_demo_prints_accuracy(short_demo, tmp_path):
    r = livecap("demo", "--recordings", str(short_demo), "--out", str(tmp_path / "w.csv"))
    assert r.returncode == 0, r.stderr
    assert "weight RMSE" in r.stdout and "vertex error (mm)" in r.stdout
    rmse = float(r.stdout.split("weight RMSE")[1].split()[0])
    assert 0 < rmse < 0.5


def test_info_on_rig_and_take(short_demo):
    r = livecap("info", str(short_demo / "demo_rig.npz"))
    assert r.returncode == 0 and "43 shapes" in r.stdout and "stable" in r.stdout
    r = livecap("info", str(short_demo / "demo_take.c3d"))
    assert r.returncode == 0 and "480 frames" in r.stdout


def test_bad_file_is_one_clear_line(tmp_path):
    (tmp_path / "bad.c3d").write_bytes(b"garbage" * 10)
    r = livecap("info", str(tmp_path / "bad.c3d"))
    assert r.returncode == 1
    assert "bad.c3d" in r.stderr and "Traceback" not in r.stderr


def test_solve_converts_the_modes_seconds_at_the_takes_rate(short_demo, tmp_path):
    """A take recorded at another rate than the calibration's: `solve` builds the mode at the take's
    rate (its marker filter window and IMM are in seconds), not the profile's tuned 120 Hz."""
    from livecap.calibration.profile import Profile
    from livecap.core.take import Take
    from livecap.modes.registry import build_solver
    from livecap.offline.solve import solve_take
    from transport.takefile import read_take, write_take

    rig, take_path, profile_path = short_demo / "demo_rig.npz", short_demo / "demo_take.c3d", tmp_path / "p.npz"
    r = livecap("calibrate", str(short_demo / "demo_neutral.c3d"), "--rig", str(rig), "--tune", str(take_path),
                "--out", str(profile_path))
    assert r.returncode == 0, r.stderr
    take = read_take(take_path)
    slow = Take(take.labels, take.positions[::2], take.valid[::2], take.rate / 2, 0)
    write_take(slow, tmp_path / "slow.c3d")
    r = livecap("solve", str(tmp_path / "slow.c3d"), "--rig", str(rig), "--profile", str(profile_path),
                "--out", str(tmp_path / "w.csv"))
    assert r.returncode == 0, r.stderr
    _, W, _ = read_weights_csv(tmp_path / "w.csv")
    profile = Profile.load(profile_path)
    assert profile.settings["robust"]["rate"] == 120.0
    slow = read_take(tmp_path / "slow.c3d")
    at_60 = solve_take(slow, profile, build_solver("robust", profile, {"rate": 60.0})).weights
    at_120 = solve_take(slow, profile, build_solver("robust", profile, {})).weights
    assert np.abs(at_60 - at_120).max() > 1e-3
    assert np.abs(W - at_60).max() < 1e-5  # the CSV's precision
