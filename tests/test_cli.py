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


def test_solve_with_a_profile_does_not_read_the_rig_meshes(short_demo, tmp_path):
    """The profile holds the calibrated basis and the labels: with it, a CSV solve leaves the rig's meshes unread
    (for a real rig, seconds of OBJ parsing), and gives the same weights as with the rig read."""
    prof = tmp_path / "actor.npz"
    r = livecap("calibrate", str(short_demo / "demo_take.c3d"), "--rig", str(short_demo / "demo_rig.npz"),
                "--out", str(prof))
    assert r.returncode == 0, r.stderr
    take = str(short_demo / "demo_take.c3d")
    r = livecap("solve", take, "--rig", str(short_demo / "demo_rig.npz"), "--profile", str(prof),
                "--out", str(tmp_path / "a.csv"))
    assert r.returncode == 0, r.stderr
    broken = tmp_path / "broken_rig.npz"
    broken.write_bytes(b"not a rig")
    r = livecap("solve", take, "--rig", str(broken), "--profile", str(prof), "--out", str(tmp_path / "b.csv"))
    # the rig must be the profile's (issue 35): its names and neutral are read, never its shapes
    assert r.returncode == 1 and "broken_rig.npz" in r.stderr and "Traceback" not in r.stderr
    r = livecap("solve", take, "--rig", str(broken), "--profile", str(prof), "--out", str(tmp_path / "c.glb"))
    assert r.returncode == 1 and "broken_rig.npz" in r.stderr and "Traceback" not in r.stderr  # a .glb needs meshes
    r = livecap("solve", take, "--rig", str(tmp_path / "nowhere"), "--profile", str(prof),
                "--out", str(tmp_path / "d.csv"))
    assert r.returncode == 1 and "nowhere" in r.stderr and "Traceback" not in r.stderr
