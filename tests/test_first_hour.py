"""Issue 21, a user's first hour: each finding's fix, checked the way the user met it."""

import logging
from pathlib import Path

import numpy as np
import pytest

from livecap.calibration.profile import Profile
from livecap.cli import main
from livecap.modes.registry import build_solver
from livecap.modes.robust_movement import RobustMovement

REC = Path(__file__).resolve().parents[1] / "recordings"
RIG = str(REC / "demo_rig.npz")


@pytest.fixture(scope="module")
def profile_path(demo_profile_path):
    """The profile docs/calibration.md's first command writes: ``calibrate`` with no --tune."""
    return str(demo_profile_path)


@pytest.fixture(scope="module")
def plain_profile(profile_path):
    return Profile.load(profile_path)


def test_plain_calibrate_stores_the_noise_estimate(plain_profile):
    """Finding 1: the plain profile carries the noise estimate, so movement is the noise-robust solve."""
    noise = plain_profile.settings["robust"]["noise_mm"]
    assert 0.4 < noise < 0.6  # the demo's markers carry 0.5 mm noise
    assert isinstance(build_solver("movement", plain_profile), RobustMovement)


def test_a_mode_that_falls_back_says_so_once(plain_profile, caplog):
    old = Profile(**{**vars(plain_profile), "settings": {k: v for k, v in plain_profile.settings.items()
                                                          if k != "robust"}})
    for mode in ("movement", "robust"):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            build_solver(mode, old)
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1 and "no noise estimate" in warnings[0].getMessage()
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        build_solver("movement", old, {"robust": False})  # --plain asked for it: nothing to say
        build_solver("movement", plain_profile)
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]


@pytest.fixture(scope="module")
def short_take(tmp_path_factory):
    from transport.takefile import read_take, write_take

    out = tmp_path_factory.mktemp("take") / "short.c3d"
    write_take(read_take(REC / "demo_take.c3d").slice(0, 1200), out)
    return out


def test_solve_and_evaluate_agree_to_the_digit(short_take, profile_path, tmp_path):
    """Finding 8: one definition of the solved take (gap-filled markers) for solve and evaluate."""
    import json

    from livecap.demo.performance import GroundTruth
    from transport.weights_csv import read_weights_csv

    truth = str(REC / "demo_take.truth.npz")
    assert main(["evaluate", str(short_take), "--rig", RIG, "--truth", truth, "--modes", "qp",
                 "--profile", profile_path, "--json", str(tmp_path / "e.json")]) == 0
    assert main(["solve", str(short_take), "--rig", RIG, "--mode", "qp", "--profile", profile_path,
                 "--out", str(tmp_path / "w.csv")]) == 0
    _, W, _ = read_weights_csv(tmp_path / "w.csv")
    rmse = float(np.sqrt(np.mean((W - GroundTruth.load(truth).weights[:1200]) ** 2)))
    row = json.loads((tmp_path / "e.json").read_text())["rows"][0]
    assert row["weight_rmse"] == pytest.approx(rmse, rel=1e-6)


def test_evaluate_reports_worst_frames_peaks_and_bias(short_take, profile_path, tmp_path, capsys):
    """Finding 9 (and 7): vertex p95, blink / jaw peak retention, per-shape bias; no blank lines, no log lines."""
    import json

    truth = str(REC / "demo_take.truth.npz")
    assert main(["evaluate", str(short_take), "--rig", RIG, "--truth", truth, "--modes", "qp", "robust",
                 "--profile", profile_path, "--json", str(tmp_path / "e.json")]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert "p95 mm" in lines[1] and "blink" in lines[1] and "jaw" in lines[1]
    assert "" not in lines and not any(line.startswith(("INFO", "WARNING")) for line in lines)
    rows = {r["mode"]: r for r in json.loads((tmp_path / "e.json").read_text())["rows"]}
    robust, qp = rows["robust"], rows["qp"]
    assert robust["vertex_mm"] < robust["vertex_p95_mm"] <= robust["vertex_max_mm"]
    assert 0.7 < robust["jaw_peak"] < 1.3 and 0.7 < robust["blink_peak"] < 1.3
    assert abs(qp["bias"]["jawOpen"]) < 0.2 and "largest per-shape bias" in out


@pytest.mark.parametrize("extra", [["--mode", "rbf"], ["--mode", "qp", "--basis", "actor"]])
def test_keys_are_checked_before_any_work(extra, tmp_path, capsys):
    """Finding 4: the missing --keys is reported first (the take here does not even exist) and says where keys
    come from."""
    assert main(["solve", str(tmp_path / "absent.c3d"), "--rig", RIG, "--out", str(tmp_path / "w.csv"), *extra]) == 1
    err = capsys.readouterr().err
    assert "--keys" in err and "livecap rom" in err and "absent.c3d" not in err


def test_calibration_report_defaults_and_layout(short_take, capsys):
    """Finding 5: the default solver's mode, identical rows folded, full row labels, no leading blank lines."""
    from livecap.cli import build_parser
    from livecap.modes.registry import DEFAULT_MODE
    from livecap.offline.calibration_report import VARIANTS

    assert build_parser().parse_args(["calibration-report", "t.c3d", "--rig", RIG]).mode == DEFAULT_MODE
    assert main(["calibration-report", str(short_take), "--rig", RIG, "--stride", "8", "--mode", "qp"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("take ") and "\n\n\n" not in out
    for v in VARIANTS:
        assert f"  {v.name} " in out
    width = max(len(v.name) for v in VARIANTS)
    fit = out.split("per-frame marker fit")[1].splitlines()[1:len(VARIANTS) + 1]
    figures = [line[width + 2:] for line in fit if "identical to" not in line]
    assert len(figures) == len(set(figures)), "two variants print the same figures"


def test_output_clutter_is_gone(short_take, profile_path, tmp_path, caplog):
    """Finding 7: no blank first line from solve (piped), run without a sink warns, noise-study prints no nan."""
    import subprocess
    import sys

    from livecap.cli.noise_study import percent

    r = subprocess.run([sys.executable, "-m", "livecap", "solve", str(short_take), "--rig", RIG, "--profile",
                        profile_path, "--mode", "qp", "--out", str(tmp_path / "w.csv")],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and r.stdout.startswith(str(tmp_path / "w.csv")), repr(r.stdout[:80])
    with caplog.at_level(logging.WARNING):
        assert main(["run", "--replay", str(short_take), "--fast", "--max-frames", "10", "--rig", RIG,
                     "--profile", profile_path]) == 0
    assert any("no output" in rec.getMessage() for rec in caplog.records)
    assert percent(float("nan")) == "n/a" and percent(0.92) == "92%"


def test_a_take_of_another_rig_says_it_shares_no_labels(vendors, capsys):
    """Finding 7: a Vicon take on the demo rig is a wrong pairing, said in one line, not 8 missing labels."""
    assert main(["calibrate", str(vendors / "Vicon.c3d"), "--rig", RIG, "--out", "unused.npz"]) == 1
    err = capsys.readouterr().err
    assert "shares none of the 60 marker labels" in err and "Vicon.c3d" in err
