"""The evaluate, rom and solve commands with the per-frame modes, end to end on real files."""

from __future__ import annotations

import json
from pathlib import Path

from livecap.cli import main
from transport.takefile import read_take


def test_rom_then_solve_rbf_and_actor_qp_then_evaluate(tmp_path, capsys):
    rom = tmp_path / "rom"
    assert main(["rom", "--out", str(rom), "--rate", "60"]) == 0
    keys = rom / "demo_rom.keys.json"
    doc = json.loads(keys.read_text())
    assert doc["take"] == "demo_rom.c3d" and len(doc["keys"]) == 43
    rig = str(Path(__file__).resolve().parents[1] / "recordings" / "demo_rig.npz")
    n_frames = read_take(rom / "demo_rom.c3d").n_frames
    assert n_frames > doc["keys"][-1]["end"]
    for extra in (["--mode", "rbf", "--keys", str(keys)], ["--mode", "qp", "--basis", "actor", "--keys", str(keys)],
                  ["--mode", "qp", "--ridge", "1e-3", "--temporal", "0.5"]):
        out = tmp_path / "w.csv"
        assert main(["solve", str(rom / "demo_rom.c3d"), "--rig", rig, "--out", str(out), *extra]) == 0
        assert out.read_text().count("\n") == 1 + n_frames
    assert main(["solve", str(rom / "demo_rom.c3d"), "--rig", rig, "--out", str(tmp_path / "x.csv"),
                 "--mode", "rbf"]) == 1
    assert "needs key pairs" in capsys.readouterr().err
    table = tmp_path / "eval.json"
    assert main(["evaluate", "--frames", "240", "--keys", str(keys), "--modes", "qp", "rbf",
                 "--json", str(table)]) == 0
    text = capsys.readouterr().out
    assert "qp actor-basis" in text and "rbf" in text and "weight RMSE" in text
    rows = {r["mode"]: r for r in json.loads(table.read_text())["rows"]}
    offline = {"qp", "rbf", "qp actor-basis", "qp ridge1 temp20"}
    assert set(rows) == offline | {f"{m} stream" for m in offline}
    assert {rows[m]["kind"] for m in offline} == {"offline"} and rows["qp stream"]["kind"] == "stream"
    assert all(0 <= r["weight_rmse"] < 0.5 for r in rows.values())
