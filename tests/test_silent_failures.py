"""Issue 35 item 6: what used to pass silently is now one line naming the file and the problem."""

from __future__ import annotations

import json

import numpy as np
import pytest

from livecap.calibration.profile import CalibrationError, calibrate
from livecap.cli import main
from livecap.core.markers import LayoutError, MarkerLayout
from livecap.core.rig import Rig
from tests.conftest import ROOT

RIG = str(ROOT / "recordings" / "demo_rig.npz")
LAYOUT = str(ROOT / "recordings" / "demo_rig.markers.json")
NEUTRAL = str(ROOT / "recordings" / "demo_neutral.c3d")
TAKE = str(ROOT / "recordings" / "demo_take.c3d")


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def _write_layout(tmp_path, name: str, data: dict) -> str:
    path = tmp_path / name
    path.write_text(json.dumps(data))
    return str(path)


def _solve(profile, tmp_path, rig: str = RIG, markers: str | None = None) -> int:
    """``livecap solve`` of the demo take with ``--profile`` (and ``--markers`` when given): its exit code."""
    return main(["solve", TAKE, "--profile", str(profile), "--rig", str(rig),
                 *(["--markers", markers] if markers else []), "--out", str(tmp_path / "w.csv")])


def _dup_layout(tmp_path) -> tuple[str, str, str]:
    data = json.loads(open(LAYOUT).read())
    a, b = data["markers"][3], data["markers"][4]
    a["vertex"] = b["vertex"]
    return _write_layout(tmp_path, "dup.json", data), a["label"], b["label"]


def test_two_markers_on_one_vertex_is_an_error_naming_file_and_labels(tmp_path, capsys):
    path, a, b = _dup_layout(tmp_path)
    with pytest.raises(LayoutError, match=f"{path}: markers {a} and {b} are bound to the same rig point"):
        MarkerLayout.load(path)
    code = main(["calibrate", NEUTRAL, "--rig", RIG, "--markers", path, "--out", str(tmp_path / "p.npz")])
    assert code == 1 and not (tmp_path / "p.npz").exists()
    err = _one_error_line(capsys)
    assert path in err and a in err and b in err


def test_calibrate_refuses_coincident_sites_and_an_exploding_fit(demo):
    rig, layout = demo
    neutral = layout.sampling_matrix(rig.n_vertices) @ rig.neutral
    v = layout.vertices.copy()
    v[1] = v[0]
    dup = MarkerLayout(layout.labels, v, layout.barycentric, layout.stable)
    with pytest.raises(CalibrationError, match=f"{layout.labels[0]} and {layout.labels[1]}"):
        calibrate(rig, dup, neutral)
    for warp in ("rbf", "similarity"):
        with pytest.raises(CalibrationError, match="exploded"):  # the take in metres against a mm rig
            calibrate(rig, layout, neutral * 1e-3, warp=warp)
    assert calibrate(rig, layout, neutral * 1.1, warp="similarity").settings["scale"] == pytest.approx(1.1)


@pytest.fixture(scope="module")
def profile(demo_profile_path):
    return demo_profile_path


def test_solve_with_a_profile_refuses_another_rig(profile, tmp_path, capsys):
    rig = Rig.load(RIG)
    moved = Rig(rig.neutral + np.array([0.0, 0.0, 1.0]), rig.triangles, rig.names, rig.deltas, rig.lower, rig.upper,
                rig.inbetweens, rig.correctives)
    other = tmp_path / "other.npz"
    moved.save(other)
    capsys.readouterr()
    assert _solve(profile, tmp_path, rig=str(other)) == 1
    err = _one_error_line(capsys)
    assert str(profile) in err and str(other) in err and "calibrated against rig" in err
    assert _solve(profile, tmp_path) == 0


def test_solve_with_a_profile_refuses_other_markers(profile, tmp_path, capsys):
    data = json.loads(open(LAYOUT).read())
    data["markers"] = data["markers"][:-3]
    fewer = _write_layout(tmp_path, "fewer.json", data)
    capsys.readouterr()
    assert _solve(profile, tmp_path, markers=fewer) == 1
    err = _one_error_line(capsys)
    assert str(fewer) in err and "calibrated with" in err
    assert _solve(profile, tmp_path, markers=LAYOUT) == 0


def test_calibrate_span_takes_the_neutral_from_seconds_inside_the_take(tmp_path, capsys):
    from livecap.calibration.profile import Profile, estimate_neutral
    from transport.takefile import read_take

    out = tmp_path / "span.npz"
    assert main(["calibrate", TAKE, "--rig", RIG, "--span", "0.5:1.5", "--out", str(out)]) == 0
    take = read_take(TAKE)
    layout = MarkerLayout.load(LAYOUT)
    s0, s1 = int(round(0.5 * take.rate)), int(round(1.5 * take.rate))
    expect = estimate_neutral(take.select(layout.labels).slice(s0, s1), layout.stable)
    prof = Profile.load(out)
    assert prof.settings["neutral_frames"] == s1 - s0
    first = estimate_neutral(take.select(layout.labels), layout.stable, s1 - s0)
    got = calibrate(Rig.load(RIG), layout, expect).source_neutral
    assert np.allclose(prof.source_neutral, got) and not np.allclose(prof.source_neutral, calibrate(
        Rig.load(RIG), layout, first).source_neutral)
    capsys.readouterr()
    assert main(["calibrate", TAKE, "--rig", RIG, "--span", "5:1", "--out", str(out)]) == 1
    assert "--span 5:1" in _one_error_line(capsys)


def test_calibration_report_gives_a_residual_per_marker(capsys):
    assert main(["calibration-report", TAKE, "--rig", RIG, "--stride", "24", "--mode", "lsq"]) == 0
    out = capsys.readouterr().out.split("per-marker fit residual", 1)[1]
    rows = [line.split() for line in out.splitlines()[1:] if line.startswith("  ")]
    labels = MarkerLayout.load(LAYOUT).labels
    named = [r for r in rows if r and r[0] in labels]
    assert len(named) == len(labels)
    rms = [float(r[1]) for r in named]
    assert rms == sorted(rms, reverse=True) and all(np.isfinite(rms))


def test_solve_with_a_profile_refuses_markers_bound_elsewhere(profile, tmp_path, capsys):
    data = json.loads(open(LAYOUT).read())
    used = {m["vertex"] for m in data["markers"]}
    data["markers"][2]["vertex"] = next(v for v in range(10_000) if v not in used)
    moved = _write_layout(tmp_path, "moved.json", data)
    capsys.readouterr()
    assert _solve(profile, tmp_path, markers=moved) == 1
    err = _one_error_line(capsys)
    assert str(moved) in err and data["markers"][2]["label"] in err and "other sites" in err
