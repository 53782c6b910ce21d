"""Takes driven by real Live Link Face curves (issue 15): reader, name mapping, ground truth, oracle."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from livecap.cli import main
from livecap.core.rig import Rig
from livecap.demo import truth_path
from livecap.demo.curves_take import CurveTakeSettings, arkit_to_rig, curves_take, take_seed
from livecap.demo.performance import GroundTruth
from livecap.offline.real_eval import blink_retention, oracle_weights
from tests.conftest import SHARED
from transport.arkit import ARKIT_NAMES
from transport.llf_csv import is_llf_csv, read_llf_csv
from transport.recorders import LLF_CSV_HEADER
from transport.takefile import read_take

SHORT = SHARED / "realdata" / "performance" / "MySlate_3_Jason_Millers_iPhone.csv"


@pytest.fixture
def short_csv():
    if not SHORT.exists():
        pytest.skip(f"real performances not found at {SHORT.parent} (../shared/realdata is not beside this checkout)")
    return SHORT


def _write_llf(path, rows, header=LLF_CSV_HEADER):
    lines = [",".join(header)] + [",".join(r) for r in rows]
    path.write_text("\n".join(lines) + "\n")


def test_reader_maps_by_header_name_and_drops_lost_rows(tmp_path):
    n = len(LLF_CSV_HEADER) - 2
    jaw_right = LLF_CSV_HEADER.index("JawRight") - 2
    vals = ["0"] * n
    vals[jaw_right] = "0.7"
    rows = [["00:00:01:00.000", "61", *vals], ["00:00:01:02.000", "0"], ["00:00:01:04.000", "61", *vals]]
    _write_llf(tmp_path / "a.csv", rows)
    c = read_llf_csv(tmp_path / "a.csv")
    assert c.lost == 1 and c.head is None
    assert np.allclose(c.times, [0.0, 4 / 60])
    assert c.weights[0, ARKIT_NAMES.index("jawRight")] == pytest.approx(0.7)
    assert c.weights[0, ARKIT_NAMES.index("jawLeft")] == 0.0


def test_reader_takes_a_csv_saved_with_a_byte_order_mark(tmp_path):
    """A CSV re-saved by a spreadsheet starts with a UTF-8 BOM; both the sniffer and the reader must see the header."""
    n = len(LLF_CSV_HEADER) - 2
    rows = [["00:00:01:00.000", "61", *["0.5"] * n], ["00:00:01:01.000", "61", *["0.25"] * n]]
    _write_llf(tmp_path / "a.csv", rows)
    (tmp_path / "a.csv").write_bytes(b"\xef\xbb\xbf" + (tmp_path / "a.csv").read_bytes())
    assert is_llf_csv(tmp_path / "a.csv")
    assert read_llf_csv(tmp_path / "a.csv").weights.shape == (2, len(ARKIT_NAMES))


@pytest.mark.parametrize("text,msg", [("frame,x\n1,2\n", "no Timecode header"),
                                      ("Timecode,BlendShapeCount,EyeBlinkLeft\n", "fewer than 10")])
def test_reader_rejects_bad_files_with_their_name(tmp_path, text, msg):
    (tmp_path / "bad.csv").write_text(text)
    with pytest.raises(ValueError, match=f"bad.csv: .*{msg}"):
        read_llf_csv(tmp_path / "bad.csv")


def test_arkit_to_rig_sides_and_mapping_file():
    A = arkit_to_rig(["browInnerUp_L", "browInnerUp_R", "eyeBlink_L", "mystery"])
    bi, bl = ARKIT_NAMES.index("browInnerUp"), ARKIT_NAMES.index("eyeBlinkLeft")
    assert A[0, bi] == A[1, bi] == 1.0 and A[2, bl] == 1.0 and not A[3].any()
    A = arkit_to_rig(["mouth-corner-puller"], {"mouthSmileLeft": "mouth-corner-puller",
                                               "mouthSmileRight": "mouth-corner-puller"})
    assert A[0, ARKIT_NAMES.index("mouthSmileLeft")] == A[0, ARKIT_NAMES.index("mouthSmileRight")] == 0.5


def test_oracle_recovers_truth_without_noise_and_degrades_with_it(ict, short_csv):
    rig, layout = ict
    W = {}
    for noise in (0.0, 0.5):
        ct = curves_take(rig, layout, short_csv, CurveTakeSettings(seconds=1.0, noise_mm=noise, occlusion=0.05))
        assert (ct.weights > 0.05).sum(1).mean() > 10  # real acting is dense
        W[noise] = np.sqrt(np.mean((oracle_weights(ct, rig.lower, rig.upper) - ct.weights) ** 2))
    assert W[0.0] < 0.02 < W[0.5]


def test_blink_retention_sees_a_halved_blink():
    t = np.zeros((60, 2))
    t[20:31, 0] = np.hanning(11)
    assert blink_retention([0], 0.5 * t, t, 60.0) == pytest.approx(0.5)


def test_generate_curves_cli_writes_take_truth_and_neutral(tmp_path, short_csv, capsys):
    assert main(["generate", "--curves", str(short_csv), "--seconds", "2", "--out", str(tmp_path)]) == 0
    take = read_take(tmp_path / f"{short_csv.stem}.c3d")
    truth = GroundTruth.load(truth_path(tmp_path / f"{short_csv.stem}.c3d"))
    rig = Rig.load("recordings/demo_rig.npz")
    assert take.n_frames == 120 and truth.names == list(rig.names) and truth.weights.shape == (120, rig.n_shapes)
    assert np.load(truth_path(tmp_path / f"{short_csv.stem}.c3d"))["actor_basis"].shape == (rig.n_shapes, 60, 3)
    assert read_take(tmp_path / f"{short_csv.stem}_neutral.c3d").valid.all()


def test_realeval_cli_reports_ratios_to_the_oracle(tmp_path, short_csv, capsys):
    out = tmp_path / "r.json"
    assert main(["realeval", "--rig", "demo", "--noise", "0.5", "--seconds", "3", "--curves", str(short_csv),
                 "--modes", "robust", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [r["mode"] for r in rows] == ["oracle", "robust stream", "robust offline"]
    assert rows[0]["rmse_x"] == 1.0 and np.isfinite(rows[1]["rmse_x"]) and rows[1]["p95_mm"] > 0
    assert "| demo | 0.5 | robust stream |" in capsys.readouterr().out


def test_take_seed_is_per_file_and_draw_and_not_pythons_salted_hash():
    """realeval seeded every take with 1, so its files shared one draw (issue 41, 2026-12-06)."""
    assert len({take_seed(n, 1, d) for n in ("apfel.csv", "S07-001.csv") for d in (0, 1, 2)}) == 6
    assert take_seed("apfel.csv", 2) != take_seed("apfel.csv", 1)
    assert take_seed("/a/apfel.csv") == take_seed(Path("b") / "apfel.csv")  # the name, not where it lies
    code = "from livecap.demo.curves_take import take_seed; print(take_seed('apfel.csv', 1, 0))"
    printed = {subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONHASHSEED": h}, text=True,
                              capture_output=True, check=True, cwd=Path(__file__).resolve().parents[1]).stdout
               for h in ("1", "2")}
    assert printed == {f"{take_seed('apfel.csv', 1, 0)}\n"}


def test_each_file_and_draw_gets_its_own_noise_occlusion_and_neutral(short_csv):
    from livecap.cli.realeval import _rig

    rig, layout = _rig("demo")
    other = sorted(p for p in short_csv.parent.glob("*.csv") if p != short_csv)[0]

    def drawn(csv, draw):
        s = CurveTakeSettings(seconds=1.0, noise_mm=0.5, seed=take_seed(csv, 1, draw))
        clean, ct = (curves_take(rig, layout, csv, replace(s, noise_mm=n)) for n in (0.0, 0.5))
        return (ct.take.positions - clean.take.positions, ct.take.valid,
                ct.neutral.positions - clean.neutral.positions)

    first = drawn(short_csv, 0)
    for a, b in zip(first, drawn(short_csv, 0), strict=True):
        assert np.array_equal(a, b)  # the same file and seed: the same take
    for other_draw in (drawn(short_csv, 1), drawn(other, 0)):
        noise, valid, neutral = other_draw
        assert not np.allclose(first[0][:60], noise[:60]) and not np.array_equal(first[1][:60], valid[:60])
        assert not np.allclose(first[2], neutral)


def test_realeval_draws_report_each_row_and_the_spread(tmp_path, short_csv, capsys):
    out = tmp_path / "r.json"
    assert main(["realeval", "--rig", "demo", "--noise", "0.5", "--seconds", "1.5", "--curves", str(short_csv),
                 "--modes", "robust", "--draws", "2", "--seed", "3", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["draw"], r["mode"]) for r in rows] == [(d, m) for d in (0, 1)
                                                      for m in ("oracle", "robust stream", "robust offline")]
    assert {r["seed"] for r in rows} == {take_seed(short_csv, 3, 0), take_seed(short_csv, 3, 1)}
    assert rows[1]["rmse"] != rows[4]["rmse"]  # another draw, another error
    text = capsys.readouterr().out
    assert "per draw min-max" in text
    lo, hi = sorted(r["rmse_x"] for r in rows if r["mode"] == "robust offline")
    assert f"{lo:.2f}-{hi:.2f} /" in text


def test_ahead_of_and_never_worse_count_per_file_and_draw():
    """The acceptance counts issue 41 states per held-out file: one loss on one figure is a loss."""
    from benchmarks.prior_lopo import never_worse
    from livecap.cli.realeval import ahead_of

    def row(mode, file, draw, rmse, p95=1.0, jitter=1.0):
        return {"rig": "ict", "noise_mm": 0.5, "file": file, "draw": draw, "mode": mode, "rmse": rmse,
                "p95_mm": p95, "jitter_x": jitter}

    rows = [row("auto=kalman stream", "a", 0, 0.1), row("a2f stream", "a", 0, 0.2, 2.0, 2.0),
            row("auto=kalman stream", "a", 1, 0.1, jitter=3.0), row("a2f stream", "a", 1, 0.2, 2.0, 2.0),
            row("oracle", "a", 0, 0.3)]
    [line] = ahead_of(rows)
    assert "in 1 of 2" in line and "a draw 1 stream (jitter_x)" in line
    lopo = [{"noise_mm": 0.5, "file": f, "draw": d, "mode": "kalman offline", "prior": p, "rmse": x}
            for f, d, p, x in [("a", 0, "no prior", 0.1), ("a", 0, "prior re-centred", 0.09),
                               ("a", 1, "no prior", 0.1), ("a", 1, "prior re-centred", 0.11)]]
    [line] = never_worse(lopo)
    assert "in 1 of 2" in line and "a draw 1 +10.0 %" in line
