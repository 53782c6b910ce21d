"""Streaming figures are measured as streamed (issue 41.4): the 'stream' rows of realeval / evaluate come from the
live pipeline fed frame by frame, so no frame's weights may depend on frames the live session has not seen yet."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from livecap.calibration.profile import Profile
from livecap.cli import main
from livecap.offline.streamed import stream_take
from transport.takefile import read_take

REC = Path(__file__).resolve().parents[1] / "recordings"


@pytest.fixture(scope="module")
def profile(demo_profile_path):
    return Profile.load(demo_profile_path)


@pytest.mark.parametrize("mode", ["kalman", "robust", "robust-lag"])
def test_streamed_weights_do_not_see_the_future(profile, mode):
    """Cutting the take at frame k leaves every earlier frame's streamed weights unchanged up to the mode's own
    latency (the offline path's centred pose smoothing and gap filling would change them)."""
    take = read_take(REC / "demo_take.c3d").slice(0, 240)
    full = stream_take(take, profile, mode)
    k = 160
    cut = stream_take(take.slice(0, k), profile, mode)
    lag = 4 if mode == "robust-lag" else 1
    assert full.mode == mode and cut.weights.shape == (k, full.weights.shape[1])
    np.testing.assert_allclose(cut.weights[:k - lag], full.weights[:k - lag], atol=1e-9)
    assert cut.step_ms["p50_ms"] > 0


def test_realeval_rows_say_stream_or_offline(ict, tmp_path):
    """The realeval table names each row's path; the stream row is the live pipeline's, not the offline targets'."""
    import json

    from livecap.cli.realeval import _realdata

    csv = sorted((_realdata() / "performance").glob("*.csv"))
    if not csv:
        pytest.skip("no real performances in ../shared/realdata/performance")
    out = tmp_path / "r.json"
    assert main(["realeval", "--rig", "ict", "--noise", "0.5", "--seconds", "2", "--curves", str(csv[0]),
                 "--modes", "kalman", "--no-prior", "--bias", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [r["mode"] for r in rows] == ["oracle", "kalman stream", "kalman offline"]
    # issue 41.6: on request, per-shape bias and the truly active shapes the solve keeps
    assert all(0 <= r["active_kept"] <= r["active_true"] and len(r["bias"]) == 53 for r in rows)


def test_the_causality_check_catches_the_offline_path(profile):
    """The check above can fail: the offline path (what the stream rows used to be) changes earlier frames."""
    from livecap.modes.registry import build_solver
    from livecap.offline.solve import solve_take

    take = read_take(REC / "demo_take.c3d").slice(0, 240)
    solver = build_solver("robust", profile)
    full = solve_take(take, profile, solver).weights
    cut = solve_take(take.slice(0, 160), profile, solver).weights
    assert np.abs(cut[:159] - full[:159]).max() > 1e-6
