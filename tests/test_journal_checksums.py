"""The raw-marker journal under damage (issue 36, item 7): per-record CRC32, version 1 journals still
read, and the temporary files a kill during shutdown leaves behind removed once their process is gone."""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.cli import main as livecap_main
from livecap.core.take import MarkerFrame
from transport.recorders import (
    MarkerRecorder,
    journal_path,
    read_marker_journal,
    read_marker_recording,
    remove_stale_temporaries,
)

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
LABELS = [f"m{i}" for i in range(12)]


def _frames(n: int = 200) -> list[MarkerFrame]:
    rng = np.random.default_rng(3)
    return [MarkerFrame(100 + i, i / 120, rng.normal(size=(len(LABELS), 3)) * 50, rng.random(len(LABELS)) > 0.1)
            for i in range(n)]


def _journal(tmp: Path, name: str = "m.npz") -> tuple[Path, list[MarkerFrame]]:
    frames = _frames()
    rec = MarkerRecorder(tmp / name, LABELS, 120.0)
    for f in frames:
        rec.record(f)
    rec.fh.close()  # killed: the journal is all there is
    return journal_path(tmp / name), frames


@pytest.mark.parametrize("seed", range(10))
def test_byte_flipped_journal_recovers_only_intact_records(tmp_path, seed, capsys):
    """Before: 10 of 10 flipped journals recovered silently, markers off by up to 23 m."""
    journal, frames = _journal(tmp_path)
    data = bytearray(journal.read_bytes())
    body = data.index(b"\n") + 1
    rng = np.random.default_rng(seed)
    for i in rng.choice(np.arange(body, len(data)), 10, replace=False):
        data[i] ^= int(rng.integers(1, 256))
    journal.write_bytes(bytes(data))
    assert livecap_main(["recover", str(journal)]) == 0
    out = capsys.readouterr().out
    got = read_marker_recording(tmp_path / "m.npz")
    by_frame = {f.frame: f for f in frames}
    assert 0 < got.take.n_frames < len(frames) and f"dropped {len(frames) - got.take.n_frames} damaged" in out
    for i, fr in enumerate(got.frames):
        orig = by_frame[int(fr)]
        np.testing.assert_array_equal(got.take.valid[i], orig.valid)
        np.testing.assert_array_equal(got.take.positions[i][orig.valid], orig.positions[orig.valid])
        assert got.timestamps[i] == orig.timestamp


def test_damaged_header_is_one_error_line(tmp_path, capsys):
    journal, _ = _journal(tmp_path)
    data = journal.read_bytes()
    journal.write_bytes(data.replace(b'"m3"', b'"m9"', 1))  # a label renamed: valid JSON, wrong checksum
    assert livecap_main(["recover", str(journal)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "m.npz.partial" in err[0] and "checksum" in err[0]


def test_torn_last_record_is_reported(tmp_path, capsys):
    journal, frames = _journal(tmp_path)
    journal.write_bytes(journal.read_bytes()[:-30])
    assert livecap_main(["recover", str(journal)]) == 0
    out = capsys.readouterr().out
    assert "recovered 199 frames" in out and "every record's checksum verified" in out and "torn" in out


def test_version_1_journal_still_reads(tmp_path, capsys):
    """A journal written before checksums (version 1: no CRC on the header or records)."""
    frames = _frames(20)
    n = len(LABELS)
    fmt = f"<qd{3 * n}d{n}B"
    head = {"magic": "livecap-markers", "version": 1, "labels": LABELS, "rate": 120.0, "record": fmt}
    body = b"".join(struct.pack(fmt, f.frame, f.timestamp, *f.positions.ravel(), *f.valid.astype(np.uint8))
                    for f in frames)
    journal = tmp_path / "old.npz.partial"
    journal.write_bytes((json.dumps(head) + "\n").encode() + body)
    rec = read_marker_journal(journal)
    assert rec.dropped is None and rec.take.n_frames == 20
    valid = np.stack([f.valid for f in frames])
    np.testing.assert_array_equal(rec.take.valid, valid)
    np.testing.assert_array_equal(rec.take.positions[valid], np.stack([f.positions for f in frames])[valid])
    assert livecap_main(["recover", str(journal)]) == 0
    assert "version 1 journal: no checksums" in capsys.readouterr().out


def test_stale_temporaries_removed_only_when_their_process_is_dead(tmp_path):
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead = tmp_path / f".m.{gone.pid}.tmp.npz"
    mine = tmp_path / f".m.{os.getpid()}.tmp.npz"
    other = tmp_path / f".n.{gone.pid}.tmp.npz"  # another target's
    for p in (dead, mine, other):
        p.write_bytes(b"PK half an archive")
    assert remove_stale_temporaries(tmp_path / "m.npz") == [dead]
    assert not dead.exists() and mine.exists() and other.exists()
    MarkerRecorder(tmp_path / "n.npz", LABELS, 120.0).fh.close()  # a new recording of n.npz cleans n's
    assert not other.exists() and mine.exists()


RECORDER = """
import sys, numpy as np
from livecap.core.take import MarkerFrame
from transport.recorders import MarkerRecorder
rng = np.random.default_rng(0)
rec = MarkerRecorder(sys.argv[1], [f"m{i}" for i in range(60)], 120.0)
pos, valid = rng.normal(size=(60, 3)) * 50, np.ones(60, bool)
for i in range(3000):  # 25 s at 120 Hz: the final .npz takes ~150 ms to write
    rec.record(MarkerFrame(i, i / 120, pos + rng.normal(size=(60, 3)), valid))
rec.flush()
print("closing", flush=True)
rec.close()
"""


def test_kills_during_shutdown_leave_nothing_recover_cannot_clean(tmp_path):
    """A real recording process killed 10-100 ms into its shutdown (while it writes the final file)
    leaves ``.m.PID.tmp.npz``; the next ``livecap recover`` of that target removes it (the PID is
    dead) and gives the complete recording."""
    left = 0
    for k, delay in enumerate((0.01, 0.03, 0.06, 0.1)):
        rec = tmp_path / str(k) / "m.npz"
        rec.parent.mkdir()
        proc = subprocess.Popen([sys.executable, "-c", RECORDER, str(rec)], stdout=subprocess.PIPE, text=True,
                                env=ENV)
        assert proc.stdout.readline().strip() == "closing"
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=30)
        left += len(list(rec.parent.glob(".m.*.tmp.npz")))
        journal = journal_path(rec)
        if journal.exists():
            assert livecap_main(["recover", str(journal)]) == 0
        assert read_marker_recording(rec).take.n_frames == 3000
        assert not list(rec.parent.glob(".m.*.tmp.npz")), f"temporaries left after recover ({delay * 1000:.0f} ms)"
    print(f"kills that left a temporary file: {left} of 4")
    assert left >= 1  # at least one kill landed inside the final write (else this test shows nothing)


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_any_damaged_byte_is_dropped_never_recovered_wrong(tmp_path_factory, data):
    """CRC32 catches every error burst of up to 32 bits, so one damaged byte anywhere after the
    header costs exactly its record and never changes a recovered frame."""
    folder = tmp_path_factory.mktemp("j")
    journal, frames = _journal(folder)
    raw = bytearray(journal.read_bytes())
    body = raw.index(b"\n") + 1
    at = data.draw(st.integers(body, len(raw) - 1))
    raw[at] ^= data.draw(st.integers(1, 255))
    journal.write_bytes(bytes(raw))
    rec = read_marker_journal(journal)
    size = (len(raw) - body) // len(frames)
    assert rec.dropped == [(at - body) // size] and rec.take.n_frames == len(frames) - 1
    kept = [f for i, f in enumerate(frames) if i != rec.dropped[0]]
    np.testing.assert_array_equal(rec.frames, [f.frame for f in kept])
    valid = np.stack([f.valid for f in kept])
    np.testing.assert_array_equal(rec.take.valid, valid)
    np.testing.assert_array_equal(rec.take.positions[valid], np.stack([f.positions for f in kept])[valid])


def test_npz_recording_claiming_a_huge_array_is_refused_before_allocating(tmp_path):
    """A 1 kB .npz whose positions header claims (100000, 10000, 3) float64: numpy allocated 22 GiB
    before reading (a MemoryError traceback under an address-space cap)."""
    import io
    import resource
    import zipfile

    from numpy.lib import format as npy

    np.savez_compressed(tmp_path / "r.npz", labels=np.array(["a", "b"]), frames=np.arange(3),
                        timestamps=np.zeros(3), positions=np.zeros((3, 2, 3)), valid=np.ones((3, 2), bool),
                        rate=np.array(120.0))
    with zipfile.ZipFile(tmp_path / "r.npz") as z:
        members = {n: z.read(n) for n in z.namelist()}
    head = io.BytesIO()
    npy.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": (10**5, 10**4, 3)})
    members["positions.npy"] = head.getvalue() + bytes(64)
    with zipfile.ZipFile(tmp_path / "bomb.npz", "w", zipfile.ZIP_DEFLATED) as z:
        for name, blob in members.items():
            z.writestr(name, blob)

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))

    code = f"from transport.recorders import read_marker_recording as r; print(r({str(tmp_path)!r} + '/r.npz')" \
           f".take.n_frames); r({str(tmp_path)!r} + '/bomb.npz')"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=60,
                         preexec_fn=cap)
    assert out.stdout.strip() == "3"
    assert "positions.npy declares (100000, 10000, 3)" in out.stderr and "MemoryError" not in out.stderr, out.stderr
