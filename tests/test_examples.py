"""examples/ run as a user runs them (a subprocess each, on short takes), and print what they say."""

from __future__ import annotations

import subprocess
import sys

from tests.conftest import ROOT
from transport.takefile import read_take, write_take

REC = ROOT / "recordings"
RIG = str(REC / "demo_rig.npz")


def _run(script: str, *args: str) -> str:
    r = subprocess.run([sys.executable, str(ROOT / "examples" / script), *args], capture_output=True, text=True,
                       cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_solve_folder_prints_a_row_per_take(tmp_path):
    take = read_take(REC / "demo_take.c3d")
    for i, start in enumerate((0, 600)):
        write_take(take.slice(start, start + 360), tmp_path / f"take{i}.c3d")
    out = _run("solve_folder.py", str(tmp_path), "--rig", RIG, "--out", str(tmp_path / "out"))
    rows = out.splitlines()
    assert [r.split()[:2] for r in rows[1:]] == [["take0", "360"], ["take1", "360"]]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["take0.csv", "take1.csv"]


def test_live_session_with_a_custom_sink():
    out = _run("live_custom_sink.py", str(REC / "demo_take.c3d"), "--rig", RIG, "--frames", "1200")
    assert "jaw opens" in out and "frames in 1200, out 1200" in out


def test_prior_and_modes_compared():
    out = _run("prior_compare_modes.py", str(REC / "demo_take.c3d"), "--rig", RIG, "--neutral",
               str(REC / "demo_neutral.c3d"), "--frames", "480")
    rmse = {line[:28].strip(): float(line.split()[-1]) for line in out.splitlines()[1:]}
    assert set(rmse) == {"robust", "qp ridge 0.01", "auto with prior (kalman)"}
    assert all(0 < v < 0.3 for v in rmse.values())
