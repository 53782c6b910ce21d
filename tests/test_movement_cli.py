"""``livecap solve --mode movement [--stream]``, ``livecap edit`` and the Fig. 11 comparison."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from livecap.cli import main
from livecap.cli.fig11 import BOUNDED, SOFT, compare, plot, table
from transport.weights_csv import read_weights_csv, write_weights_csv

REC = Path(__file__).resolve().parents[1] / "recordings"


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    out = tmp_path_factory.mktemp("mm")
    args = [str(REC / "demo_take.c3d"), "--rig", str(REC / "demo_rig.npz")]
    assert main(["solve", *args, "--mode", "movement", "--out", str(out / "off.csv")]) == 0
    assert main(["solve", *args, "--mode", "movement", "--stream", "--window", "12", "--lookahead", "3",
                 "--out", str(out / "st.csv")]) == 0
    return out, args


def test_solve_writes_offline_and_streaming_curves(solved):
    out, _ = solved
    names, off, _ = read_weights_csv(out / "off.csv")
    _, st, _ = read_weights_csv(out / "st.csv")
    assert off.shape == st.shape and off.shape[1] == len(names)
    assert np.isfinite(off).all() and np.isfinite(st).all()
    assert np.allclose(off[0], 0, atol=1e-6) and np.allclose(off[-1], 0, atol=1e-6)  # neutral boundaries
    assert st.min() >= 0 and st.max() <= 1 + 1e-6  # streaming clips to the rig's limits


def test_solve_limits_clip_by_default_and_bound_on_request(solved, tmp_path):
    out, args = solved
    _, robust, _ = read_weights_csv(out / "off.csv")
    assert robust.min() >= 0 and robust.max() <= 1  # the noise-robust default solves inside the limits
    assert main(["solve", *args, "--mode", "movement", "--plain", "--out", str(tmp_path / "p.csv")]) == 0
    _, off, _ = read_weights_csv(tmp_path / "p.csv")
    assert off.min() >= 0 and off.max() <= 1  # plain Seol: clipped to the demo rig's [0, 1] by default
    assert np.abs(off - robust).max() > 0.05
    assert main(["solve", *args, "--mode", "movement", "--plain", "--limits", "bound",
                 "--out", str(tmp_path / "b.csv")]) == 0
    _, bound, _ = read_weights_csv(tmp_path / "b.csv")
    assert bound.min() >= 0 and bound.max() <= 1
    assert 0 < np.abs(bound - off).max()  # a different solution: the limits inside the solve, not after it


def test_trend_flag_sets_the_weight_trend_filter(solved, tmp_path):
    from livecap.offline.metrics import jitter

    out, args = solved
    _, smooth, _ = read_weights_csv(out / "off.csv")
    assert main(["solve", *args, "--mode", "movement", "--trend", "0", "--out", str(tmp_path / "t0.csv")]) == 0
    _, rough, _ = read_weights_csv(tmp_path / "t0.csv")
    assert jitter(rough) > 5 * jitter(smooth)  # the L1 solve's jitter (benchmark: 42 x vs 1.25 x truth)


def test_edit_with_the_source_take(solved, tmp_path):
    out, args = solved
    names, W, _ = read_weights_csv(out / "off.csv")
    spec = tmp_path / "edits.json"
    spec.write_text(json.dumps([{"frame": 1000, "weights": {"jawOpen": 0.9}, "range": [988, 1012]}]))
    assert main(["edit", str(out / "off.csv"), "--edits", str(spec), "--take", args[0], "--rig", args[2],
                 "--out", str(tmp_path / "e.csv")]) == 0
    _, E, _ = read_weights_csv(tmp_path / "e.csv")
    j = names.index("jawOpen")
    assert abs(E[1000, j] - 0.9) < 1e-6
    assert np.array_equal(E[:989], W[:989]) and np.array_equal(E[1012:], W[1012:])
    assert np.abs(E[990:1000, j] - W[990:1000, j]).max() > 0.05


def test_edit_without_a_take_spreads_the_correction_linearly(tmp_path):
    W = np.zeros((30, 2))
    write_weights_csv(tmp_path / "w.csv", ["a", "b"], W, 30.0, first_frame=100)
    assert main(["edit", str(tmp_path / "w.csv"), "--edit", "110:a=1.0@105-120", "--out", str(tmp_path / "o.csv")]) == 0
    _, E, _ = read_weights_csv(tmp_path / "o.csv")
    assert np.allclose(E[5:11, 0], np.linspace(0, 1, 6), atol=1e-6)
    assert np.allclose(E[10:21, 0], np.linspace(1, 0, 11), atol=1e-6)
    assert np.array_equal(E[:, 1], W[:, 1])


def test_edit_reports_bad_input(tmp_path, capsys):
    write_weights_csv(tmp_path / "w.csv", ["a"], np.zeros((10, 1)), 30.0)
    assert main(["edit", str(tmp_path / "w.csv"), "--edit", "5:nope=1", "--out", str(tmp_path / "o.csv")]) == 1
    assert "unknown shapes" in capsys.readouterr().err


def test_fig11_compare_table_and_plot(tmp_path, demo):
    rig, layout = demo
    B = layout.basis(rig)
    rng = np.random.default_rng(0)
    T, n = 120, layout.n_markers
    W = np.clip(np.sin(np.linspace(0, 6, T))[:, None] * rng.random(rig.n_shapes), 0, 1)
    S = (W @ B.T).reshape(T, n, 3) + rng.normal(0, 0.5, (T, n, 3))
    valid = rng.random((T, n)) > 0.02
    res = compare(B, S, valid, -0.5, 1.5)
    assert set(res["velocity"]) == {"No Const", "Range PF", "Prior PF", BOUNDED, SOFT}
    for name in ("Range PF", "Prior PF", BOUNDED, SOFT):
        assert res["weights"][name].min() >= -0.5 - 0.006 and res["weights"][name].max() <= 1.5 + 0.006
        assert res["velocity"][name].sum() >= res["velocity"]["No Const"].sum() - 1e-6  # No Const is optimal
    assert BOUNDED in table(res, -0.5, 1.5)
    plot(res, 120.0, tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 10_000
