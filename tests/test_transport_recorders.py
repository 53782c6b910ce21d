"""Recorders read back what they were given; torn tails and killed sessions lose nothing flushed."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.core.result import SolveResult
from livecap.core.take import MarkerFrame
from transport.arkit import ARKIT_NAMES
from transport.recorders import (
    LLF_CSV_HEADER,
    CsvRecorder,
    JsonlRecorder,
    MarkerRecorder,
    journal_path,
    parse_timecode,
    read_csv_recording,
    read_jsonl_recording,
    read_marker_recording,
    timecode,
)
from transport.replay import ReplaySource, open_take

RNG = np.random.default_rng(0)


def results(names, n=30, rate=120.0):
    W = RNG.uniform(0, 1, (n, len(names)))
    return [SolveResult(100 + i, i / rate, names, W[i], np.array([0, 0, 0, 1.0]), np.array([1.0, 2, 3]), 0.5, 1e-3)
            for i in range(n)], W


def test_csv_livecap_layout_round_trip(tmp_path):
    names = ["a_L", "b", "c"]
    res, W = results(names)
    rec = CsvRecorder(tmp_path / "w.csv", 120)
    for r in res:
        rec.publish(r)
    rec.close()
    back = read_csv_recording(tmp_path / "w.csv")
    assert back.layout == "livecap" and back.names == names
    np.testing.assert_array_equal(back.weights, W)
    np.testing.assert_array_equal(back.frames, [r.frame for r in res])
    np.testing.assert_array_equal(back.times, [r.timestamp for r in res])


def test_csv_live_link_face_layout_for_arkit_rigs(tmp_path):
    names = ["jawOpen", "eyeBlinkLeft", "mouthLeft", "jawRight"]
    res, W = results(names, rate=60)
    rec = CsvRecorder(tmp_path / "w.csv", 60, timecode="12:00:00:00")  # not the clock: published at once
    for r in res:
        rec.publish(r)
    rec.close()
    header = (tmp_path / "w.csv").read_text().splitlines()[0].split(",")
    assert header == LLF_CSV_HEADER and len(header) == 2 + 61
    back = read_csv_recording(tmp_path / "w.csv", rate=60)
    assert back.layout == "livelinkface"
    col = {n.lower(): i for i, n in enumerate(back.names)}
    for j, n in enumerate(names):
        np.testing.assert_allclose(back.weights[:, col[n.lower()]], W[:, j], atol=5.1e-11)  # ten decimals
    assert not back.weights[:, col["tongueout"]].any()
    np.testing.assert_allclose(back.times, [r.timestamp for r in res], atol=1e-3 / 60)
    assert set(ARKIT_NAMES) == {n[0].lower() + n[1:] for n in back.names[:52]}


@given(st.floats(0, 86000), st.sampled_from([24, 30, 60, 120]))
@settings(max_examples=100, deadline=None)
def test_timecode_round_trip(t, rate):
    assert parse_timecode(timecode(t, rate), rate) == pytest.approx(t, abs=1.01e-3 / rate)


def test_jsonl_round_trip_exact(tmp_path):
    names = ["x", "y"]
    res, W = results(names)
    rec = JsonlRecorder(tmp_path / "w.jsonl")
    for r in res:
        rec.publish(r)
    rec.close()
    back_names, frames = read_jsonl_recording(tmp_path / "w.jsonl")
    assert back_names == names and len(frames) == len(res)
    np.testing.assert_array_equal([f["weights"] for f in frames], W)
    assert frames[3]["frame"] == 103 and frames[3]["head_translation"] == [1.0, 2.0, 3.0]


def test_flushed_counts_only_what_reached_the_os(tmp_path):
    res, _ = results(["x"], 10)
    rec = JsonlRecorder(tmp_path / "w.jsonl")
    for r in res[:4]:
        rec.publish(r)
    assert rec.flushed == 0
    rec.flush()
    assert rec.flushed == 4 and len(read_jsonl_recording(tmp_path / "w.jsonl")[1]) == 4
    rec.close()


def test_torn_last_line_is_ignored(tmp_path):
    names = ["x", "y"]
    res, W = results(names, 5)
    rec = CsvRecorder(tmp_path / "w.csv", 120, layout="livecap")
    for r in res:
        rec.publish(r)
    rec.close()
    text = (tmp_path / "w.csv").read_text()
    (tmp_path / "w.csv").write_text(text[:-7])
    back = read_csv_recording(tmp_path / "w.csv")
    np.testing.assert_array_equal(back.weights, W[:4])


def test_marker_recording_npz_and_journal_recovery(tmp_path):
    labels = ["a", "b", "c"]
    rec = MarkerRecorder(tmp_path / "m.npz", labels, 120)
    frames = []
    for i in range(20):
        pos = RNG.normal(size=(3, 3)) * 100
        val = RNG.uniform(size=3) > 0.2
        f = MarkerFrame(50 + 2 * i, 0.1 + i / 60, np.where(val[:, None], pos, 0.0), val)
        frames.append(f)
        rec.record(f)
    rec.flush()
    # a session killed here leaves the journal: recover it
    partial = read_marker_recording(journal_path(tmp_path / "m.npz"))
    assert partial.take.n_frames == 20
    rec.close()
    assert not journal_path(tmp_path / "m.npz").exists()
    back = read_marker_recording(tmp_path / "m.npz")
    np.testing.assert_array_equal(back.frames, [f.frame for f in frames])
    np.testing.assert_array_equal(back.timestamps, [f.timestamp for f in frames])
    np.testing.assert_array_equal(back.take.positions, np.stack([f.positions for f in frames]))
    np.testing.assert_array_equal(back.take.valid, np.stack([f.valid for f in frames]))
    # a replay reproduces the frames exactly, numbers and timestamps included
    out = list(ReplaySource.open(tmp_path / "m.npz", fast=True))
    assert [f.frame for f in out] == [f.frame for f in frames]
    np.testing.assert_array_equal(out[7].positions, frames[7].positions)


def test_marker_recording_c3d(tmp_path):
    rec = MarkerRecorder(tmp_path / "m.c3d", ["a", "b"], 100)
    for i in range(5):
        rec.record(MarkerFrame(i, i / 100, np.full((2, 3), float(i)), np.array([True, i % 2 == 0])))
    rec.close()
    take, frames, _ = open_take(tmp_path / "m.c3d")
    assert take.n_frames == 5 and take.rate == 100 and take.labels == ["a", "b"]
    assert take.valid[:, 1].tolist() == [True, False, True, False, True]
    np.testing.assert_allclose(take.positions[3, 0], [3, 3, 3], atol=1e-4)


def test_replay_paces_loops_and_slices(tmp_path):
    from livecap.core.take import Take

    take = Take(["a"], np.arange(12, dtype=float).reshape(12, 1, 1).repeat(3, 2), np.ones((12, 1), bool), 100.0, 10)
    src = ReplaySource(take, loop=True, start=12, end=16, speed=2.0)
    out = []
    import time

    t0 = time.perf_counter()
    for f in src:
        out.append(f)
        if len(out) == 10:
            src.stop()
    took = time.perf_counter() - t0
    assert [f.frame for f in out] == [12, 13, 14, 15, 16, 17, 18, 19, 20, 21]
    assert out[4].positions[0, 0] == 2.0  # the loop restarts at frame 12's data
    assert all(b.timestamp > a.timestamp for a, b in zip(out, out[1:], strict=False))
    assert took >= 9 / 200 * 0.9  # paced at rate x speed, never faster
    with pytest.raises(ValueError, match="no frames"):
        ReplaySource(take, start=100)
