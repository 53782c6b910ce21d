"""The Live Link Face app's CSV as a take (issue 40 item 1) and ARKit curves onto any rig (item 2): by name,
by a mapping file, by expression transfer through the ICT face; ``livecap solve`` on the real app CSVs."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from livecap.cli import main
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.retarget import ByName, ExpressionTransfer
from tests.conftest import ICT, ROOT, SHARED
from transport.arkit import ARKIT_NAMES, load_mapping
from transport.errors import TakeFileError
from transport.llf_csv import read_llf_csv
from transport.recorders import LLF_CSV_HEADER
from transport.takefile import read_take
from transport.weights_csv import read_weights_csv

PERF = SHARED / "realdata" / "performance"
MH = SHARED / "realdata" / "makehuman-head"
MAP = ROOT / "examples" / "makehuman_arkit.json"


def _real(name: str):
    path = PERF / name
    if not path.exists():
        pytest.skip(f"{path} absent (real Live Link Face CSVs, ../shared/realdata)")
    return path


def _rigs():
    if not (MH / "neutral.obj").exists() or not (ICT / "neutral.obj").exists():
        pytest.skip(f"MakeHuman head or ICT rig absent under {SHARED / 'realdata'}")
    return Rig.load(MH), Rig.load(ICT)


def _write(path, rows):
    path.write_text("\n".join(",".join(r) for r in [LLF_CSV_HEADER, *rows]) + "\n")


def _row(tc: str, jaw: str = "0.5", eye_yaw: str = "0.2") -> list[str]:
    vals = ["0"] * (len(LLF_CSV_HEADER) - 2)
    vals[LLF_CSV_HEADER.index("JawOpen") - 2] = jaw
    vals[LLF_CSV_HEADER.index("LeftEyeYaw") - 2] = eye_yaw
    return [tc, "61", *vals]


def test_bad_rows_are_counted_not_fatal_and_eyes_and_timecode_kept(tmp_path):
    good = [_row("10:00:00:01.000"), _row("10:00:00:03.000", "0.7"), _row("10:00:00:05.000", "0.9", "-0.1")]
    rows = [good[0], ["10:00:00:02.000", "0"], _row("10:00:00:02.500", "zero"), good[1], good[2][:30],
            _row("xx:00", "0.1"), _row("10:00:00:04.000", "nan"), good[2]]
    _write(tmp_path / "take.csv", rows)
    c = read_llf_csv(tmp_path / "take.csv")
    assert (c.lost, c.bad) == (1, 4) and c.first_bad.startswith("line 4:")
    assert np.allclose(c.weights[:, ARKIT_NAMES.index("jawOpen")], [0.5, 0.7, 0.9])
    assert np.allclose(c.eyes[:, 0], [0.2, 0.2, -0.1]) and c.head is None
    assert c.first_frame == 10 * 3600 * 60 + 1


def test_not_an_llf_csv_or_a_broken_one_is_one_line(tmp_path, capsys):
    _write(tmp_path / "broken.csv", [_row("bad")])
    (tmp_path / "markers.csv").write_text("frame,x\n1,2\n")
    for name, msg in [("broken.csv", "fewer than two tracked rows; 1 unreadable rows, first line 2"),
                      ("markers.csv", "markers.csv")]:
        assert main(["solve", str(tmp_path / name), "--rig", str(ROOT / "recordings" / "demo_rig.npz"),
                     "--out", str(tmp_path / "w.csv")]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and msg in err and "Traceback" not in err


def test_a_marker_command_names_an_llf_csv_as_weights(tmp_path):
    _write(tmp_path / "take.csv", [_row("10:00:00:01.000"), _row("10:00:00:03.000")])
    with pytest.raises(TakeFileError, match="take.csv: a Live Link Face CSV holds ARKit weights, not markers"):
        read_take(tmp_path / "take.csv")


def test_solve_by_name_keeps_every_row_and_the_timecode(tmp_path, capsys):
    """The real S88 take (277 tracking-lost rows) onto ICT by name: each app row's weight at its timecode frame."""
    path = _real("S88-001.csv")
    if not (ICT / "neutral.obj").exists():
        pytest.skip(f"ICT rig absent at {ICT}")
    out = tmp_path / "w.csv"
    assert main(["solve", str(path), "--rig", str(ICT), "--out", str(out)]) == 0
    assert "277 tracking lost" in capsys.readouterr().out
    names, W, _ = read_weights_csv(out)
    frames = np.loadtxt(out, delimiter=",", skiprows=1, usecols=0).astype(int)
    with open(path, newline="") as fh:
        header, *rows = list(csv.reader(fh))
    tracked = [r for r in rows if len(r) > 2]
    tc = np.array([[float(x) for x in r[0].split(":")] for r in tracked])
    seconds = ((tc[:, 0] * 60 + tc[:, 1]) * 60 + tc[:, 2]) + tc[:, 3] / 60
    assert frames[0] == round(seconds[0] * 60)
    assert (np.diff(frames) == 1).all() and len(frames) == int((seconds[-1] - seconds[0]) * 60 + 1e-6) + 1
    jaw = np.array([float(r[header.index("JawOpen")]) for r in tracked])  # by the file's own header
    grid = seconds[0] + np.arange(len(frames)) / 60
    assert np.allclose(W[:, names.index("jawOpen")], np.interp(grid, seconds, jaw), atol=1e-6)
    assert W[0, names.index("jawOpen")] == pytest.approx(jaw[0], abs=1e-6)


def test_makehuman_by_name_is_refused_by_map_and_transfer_are_solved(tmp_path, capsys):
    mh, _ = _rigs()
    path = _real("MySlate_3_Jason_Millers_iPhone.csv")
    args = ["solve", str(path), "--rig", str(MH), "--out"]
    assert main([*args, str(tmp_path / "n.csv")]) == 1
    assert "none of its 34 shapes takes an ARKit name" in capsys.readouterr().err
    assert main([*args, str(tmp_path / "m.csv"), "--map", str(MAP)]) == 0
    assert main([*args, str(tmp_path / "t.csv"), "--transfer", str(ICT)]) == 0
    names, Wm, _ = read_weights_csv(tmp_path / "m.csv")
    _, Wt, _ = read_weights_csv(tmp_path / "t.csv")
    assert names == mh.names and Wm.shape == Wt.shape
    mapped = set(np.concatenate([[v] if isinstance(v, str) else v for v in load_mapping(MAP).values()]))
    assert not Wm[:, [n not in mapped for n in names]].any()  # the map drives only what it names
    assert Wt[:, [n not in mapped for n in names]].any()  # transfer fits units no name reaches
    jaw = names.index("mouth-open")
    assert np.corrcoef(Wm[:, jaw], Wt[:, jaw])[0, 1] > 0.8


def test_transfer_onto_ict_itself_gives_back_the_weights():
    """ICT through its own marker sites: the fitted weights are the driving ones (the ridge shrinks them a little)."""
    _, ict = _rigs()
    layout = MarkerLayout.load(ICT / "markers.json", ict)
    arkit = read_llf_csv(_real("MySlate_3_Jason_Millers_iPhone.csv")).resample(30)[0]
    W = ExpressionTransfer(ict, layout, ict, layout).apply(arkit)
    truth = ByName(ict).apply(arkit)
    assert np.sqrt(np.mean((W - truth) ** 2)) < 0.1
    move = ict.evaluate(truth) - ict.neutral
    err = ict.evaluate(W) - ict.evaluate(truth)
    assert np.sqrt(np.mean(err ** 2)) < 0.25 * np.sqrt(np.mean(move ** 2))


def test_replay_renders_an_llf_csv_on_makehuman_by_its_timecode_frames(tmp_path):
    _rigs()
    path = _real("MySlate_3_Jason_Millers_iPhone.csv")
    assert main(["replay", str(path), "--rig", str(MH), "--map", str(MAP), "--frames", str(tmp_path),
                 "--every", "60", "--size", "64x48", "--msaa", "0"]) == 0
    first = read_llf_csv(path).first_frame
    pngs = sorted(tmp_path.glob("frame_*.png"))
    assert [p.name for p in pngs[:2]] == [f"frame_{first}.png", f"frame_{first + 60}.png"]


def test_review_serves_an_llf_csv_on_makehuman_by_transfer_with_its_timecode(tmp_path):
    """A real ``livecap review`` on the app's CSV: the curves' frames, the first timecode frame, every shape, and
    virtual markers that the weights explain (residual ~0) for the edits to re-solve against."""
    import json
    import subprocess
    import sys
    import urllib.request

    _rigs()
    path = _real("MySlate_3_Jason_Millers_iPhone.csv")
    cmd = [sys.executable, "-m", "livecap", "review", str(path), "--rig", str(MH), "--transfer", str(ICT),
           "--port", "0", "--no-browser", "--journal", str(tmp_path / "j")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert "http://" in line, proc.stderr.read() if proc.poll() is not None else line
        base, _, token = line.split(" at ")[-1].strip().partition("?token=")

        def get(p):
            req = urllib.request.Request(base.rstrip("/") + p, headers={"X-Livecap-Token": token})
            with urllib.request.urlopen(req, timeout=60) as r:
                return json.loads(r.read())
        meta, curves = get("/api/meta"), get("/api/curves")
    finally:
        proc.terminate()
        proc.wait(10)
    c = read_llf_csv(path)
    assert meta["first_frame"] == c.first_frame and meta["names"] == Rig.load(MH).names
    assert meta["n_frames"] == int(c.times[-1] * 60 + 1e-6) + 1
    assert max(curves["residual"]) < 1e-3 and np.abs(np.array(curves["weights"])).max() > 0.1
