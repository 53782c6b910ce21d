"""The review session's edit journal: checksummed lines, a corrupt tail skipped and counted, a
journal of another solve refused, and a killed ``livecap review`` reopening with its edits."""

from __future__ import annotations

import signal

import numpy as np
import pytest

from livecap.review.journal import EditJournal, fingerprint, open_journal


def write(path, n):
    j = EditJournal(path, "fp")
    for i in range(n):
        j.append({"op": "edit", "id": i + 1, "a": i, "b": i, "after": [[0.1 * i]]})
    j.close()


def test_a_corrupt_tail_is_skipped_counted_and_cut(tmp_path):
    path = tmp_path / "take.review-edits"
    write(path, 5)
    data = bytearray(path.read_bytes())
    lines = data.splitlines(keepends=True)
    at = sum(map(len, lines[:4])) + 20  # a byte of the 4th edit (line 5) flipped
    data[at] ^= 0x04
    path.write_bytes(bytes(data) + b'0000 {"torn')
    j = EditJournal(path, "fp")
    assert [e["id"] for e in j.entries] == [1, 2, 3] and j.skipped == 3
    j.append({"op": "undo", "id": 3})
    j.close()
    again = EditJournal(path, "fp")
    assert [e.get("op") for e in again.entries] == ["edit", "edit", "edit", "undo"] and again.skipped == 0


def test_another_solves_journal_is_set_aside_never_replayed(tmp_path):
    path = tmp_path / "take.review-edits"
    write(path, 1)
    kept = path.read_bytes()
    with pytest.raises(ValueError, match="another solve"):
        EditJournal(path, "other")
    j, notice = open_journal(path, "other")
    assert j.entries == [] and "another solve" in notice
    j.close()
    (aside,) = [p for p in tmp_path.iterdir() if p != path]
    assert aside.read_bytes() == kept and str(aside) in notice
    path.write_bytes(b"garbage\n")
    with pytest.raises(ValueError, match="not a livecap review journal"):
        EditJournal(path, "fp")


def test_one_server_at_a_time(tmp_path):
    path = tmp_path / "take.review-edits"
    j = EditJournal(path, "fp")
    with pytest.raises(ValueError, match="in use"):
        EditJournal(path, "fp")
    j.close()
    EditJournal(path, "fp").close()


def test_fingerprint_tells_solves_apart():
    W = np.zeros((3, 2))
    assert fingerprint(["a", "b"], W) != fingerprint(["a", "c"], W)
    assert fingerprint(["a", "b"], W) != fingerprint(["a", "b"], W + 1e-12)


def test_killed_server_reopens_with_its_edits(review_server, tmp_path):
    from tests.review_server import ReviewServer

    work = review_server.journal.parent  # its calibrated profile: no second calibration
    journal = tmp_path / "take.review-edits"
    first = ReviewServer(work, journal=journal)
    try:
        for k, v in ((300, 0.9), (600, 0.7), (900, 0.5)):
            assert first.request("/api/edit", {"frame": k, "weights": {"jawOpen": v}, "range": [k - 10, k + 10]},
                                 client="tab")[0] == 200
        assert first.request("/api/undo", {}, client="tab")[0] == 200
        edited = first.request("/export/weights.csv")[1]
        first.proc.send_signal(signal.SIGKILL)
        first.proc.wait(30)
    finally:
        first.close()
    with open(journal, "ab") as fh:
        fh.write(b"deadbeef {\"op\": \"edit\"")  # a line torn by the kill
    second = ReviewServer(work, journal=journal)
    try:
        assert second.notices == [f"livecap review: replayed 4 journal entries (edits, undos, redos) from "
                                  f"{journal}; skipped a corrupt tail "
                                  "of 1 lines"]
        assert second.request("/export/weights.csv")[1] == edited
        assert second.request("/api/curves", client="tab")[1]["undo"] == 2  # the tab's history came back
        assert second.request("/api/redo", {}, client="tab")[0] == 200
    finally:
        second.close()
