"""Hostile input at the source level (issue 17): restarts, lies, poisoning, floods, truncation.

Real ZeroMQ and UDP sockets on loopback inside one process; the cross-process cases are in
tests/test_hostile_cli.py.
"""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest
import zmq

from transport.osc_source import OscDecodeError, OscSource, decode_osc_frame, encode_osc_frame
from transport.wire import (
    LAYOUT_TABLE_SIZE,
    MAX_MESSAGE_BYTES,
    LayoutMismatch,
    LayoutTable,
    Oversize,
    decode_markers,
    encode_markers,
    layout_id,
    topic,
)
from transport.zmq_source import ZmqSource

LABELS = [f"m{i:02d}" for i in range(20)]
TP = topic("markers", "actor")
RNG = np.random.default_rng(17)
POS = RNG.normal(0, 30, (len(LABELS), 3))
VALID = np.ones(len(LABELS), bool)


@pytest.fixture
def zmq_pair():
    ctx = zmq.Context()
    pub = ctx.socket(zmq.XPUB)
    pub.bind("tcp://127.0.0.1:*")
    src = ZmqSource(pub.getsockopt(zmq.LAST_ENDPOINT).decode(), LABELS, context=ctx, idle_timeout=0.5)
    assert pub.poll(5000) and pub.recv() == b"\x01markers.actor"
    yield pub, src
    src.close()
    pub.close(0)
    ctx.term()


def good(frame: int, ts: float | None = None, labels=LABELS, lid=None) -> bytes:
    return encode_markers(frame, frame / 120 if ts is None else ts, POS, VALID, labels, lid)


def drain(src) -> list:
    return [f.frame for f in src]  # ends after idle_timeout without a good frame


def test_restarted_sender_is_solved_again(zmq_pair):
    pub, src = zmq_pair
    for f in [*range(1000, 1100), *range(0, 50)]:  # the sender restarted: frame numbers start low
        pub.send_multipart([TP, good(f)])
    frames = drain(src)
    assert frames == [*range(1000, 1100), *range(0, 50)]
    assert src.bad.counts["stream_restart"] == 1


def test_one_far_future_frame_is_ignored(zmq_pair):
    pub, src = zmq_pair
    for f in [0, 1, 2**40, *range(2, 100)]:
        pub.send_multipart([TP, good(f)])
    assert drain(src) == list(range(100))
    assert src.bad.counts["frame_outlier"] == 1 and src.bad.counts["stream_restart"] == 0


def test_layout_id_that_does_not_match_its_labels_is_refused():
    table = LayoutTable()
    lid = layout_id(LABELS)
    with pytest.raises(LayoutMismatch):  # the id of LABELS sent with the labels reversed
        decode_markers(good(0, labels=LABELS[::-1], lid=lid), table)
    assert lid not in table
    decode_markers(good(1, labels=LABELS, lid=lid), table)
    assert decode_markers(encode_markers(2, 0.0, POS, VALID, layout=lid), table).labels == LABELS


def test_layout_poisoning_is_counted_and_skipped_by_the_source(zmq_pair):
    pub, src = zmq_pair
    lid = layout_id(LABELS)
    pub.send_multipart([TP, good(0, labels=LABELS[::-1], lid=lid)])
    for f in range(1, 20):
        pub.send_multipart([TP, encode_markers(f, f / 120, POS, VALID, layout=lid)])
    got = list(src)
    assert [f.frame for f in got] == list(range(1, 20))
    assert all(np.allclose(f.positions, POS, atol=1e-4) for f in got)  # in the right marker order
    assert src.bad.counts["layout_mismatch"] == 1


def test_layout_table_is_bounded():
    table = LayoutTable()
    for k in range(500):
        labels = [f"x{k}_{i}" for i in range(20)]
        decode_markers(good(k, labels=labels, lid=layout_id(labels)), table)
    assert len(table) == LAYOUT_TABLE_SIZE


def test_oversize_message_is_refused_before_decoding():
    with pytest.raises(Oversize):
        decode_markers(b"\x00" * (MAX_MESSAGE_BYTES + 1))


def test_garbage_does_not_make_valid_frames_stale(zmq_pair):
    pub, src = zmq_pair
    pub.send_multipart([TP, good(0)])
    for _ in range(200):
        pub.send_multipart([TP, b"\x93garbage"])
    time.sleep(0.2)
    it = iter(src)
    assert next(it).frame == 0
    assert not src.pending()  # only garbage waits: the frame in hand is the newest
    pub.send_multipart([TP, good(1)])
    time.sleep(0.1)
    assert src.pending() and next(it).frame == 1
    assert src.bad.counts["malformed"] == 200


def test_truncated_osc_bundle_is_refused():
    where = {lab: i for i, lab in enumerate(LABELS)}
    dgram = encode_osc_frame(3, 0.5, LABELS, POS, VALID)
    assert decode_osc_frame(dgram, where)[0] == 3
    for cut in (1, 2, 3, 4, 8, 20):
        with pytest.raises(OscDecodeError) as err:
            decode_osc_frame(dgram[:-cut], where)
        assert err.value.kind in ("short", "malformed")


@pytest.mark.parametrize("kind", ["zmq", "osc"])
def test_idle_timeout_fires_when_no_frame_ever_arrives(kind):
    ctx = zmq.Context()
    if kind == "zmq":
        src = ZmqSource("tcp://127.0.0.1:1", LABELS, context=ctx, idle_timeout=0.4)
    else:
        src = OscSource("127.0.0.1", 0, LABELS, idle_timeout=0.4)
    t0 = time.monotonic()
    assert list(src) == []
    assert time.monotonic() - t0 < 3
    src.close()
    ctx.term()


def test_osc_garbage_does_not_make_valid_frames_stale():
    src = OscSource("127.0.0.1", 0, LABELS, idle_timeout=0.5)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.sendto(encode_osc_frame(0, 0.0, LABELS, POS, VALID), src.address)
    for _ in range(100):
        tx.sendto(b"#bundle\x00garbage!", src.address)
    time.sleep(0.3)
    it = iter(src)
    assert next(it).frame == 0 and not src.pending()
    tx.close()
    src.close()


def test_final_recording_appears_atomically_or_not_at_all(tmp_path, monkeypatch):
    """A kill while the final file is written must not leave a torn file beside the journal."""
    from livecap.core.take import MarkerFrame
    from transport import recorders

    path = tmp_path / "m.npz"
    rec = recorders.MarkerRecorder(path, LABELS, 120.0)
    for f in range(30):
        rec.record(MarkerFrame(f, f / 120, POS, VALID))

    def torn(fh, **arrays):  # the process dies half-way through writing the archive
        fh.write(b"PK\x03\x04 half an archive")
        raise KeyboardInterrupt

    monkeypatch.setattr(recorders.np, "savez_compressed", torn)
    with pytest.raises(KeyboardInterrupt):
        rec.close()
    assert not path.exists() and list(tmp_path.iterdir()) == [recorders.journal_path(path)]
    monkeypatch.undo()
    out, n = recorders.recover_marker_journal(recorders.journal_path(path))
    assert out == path and n == 30 and recorders.read_marker_recording(path).take.n_frames == 30


def test_osc_garbage_cannot_fill_the_queue_and_push_out_valid_frames():
    src = OscSource("127.0.0.1", 0, LABELS, idle_timeout=0.5, queue_size=8)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for _ in range(100):
        tx.sendto(b"garbage that is not an OSC bundle", src.address)
    tx.sendto(encode_osc_frame(7, 0.0, LABELS, POS, VALID), src.address)
    assert [f.frame for f in src] == [7]
    assert src.bad.counts["malformed"] == 100 and src.bad.counts["overrun"] == 0
    tx.close()
    src.close()


def test_a_stream_sharing_no_labels_with_the_profile_is_an_error(zmq_pair):
    from transport.badinput import MISMATCH_PACKETS, LabelMismatch

    pub, src = zmq_pair
    other = [f"x{i}" for i in range(len(LABELS))]
    for f in range(MISMATCH_PACKETS + 5):
        pub.send_multipart([TP, good(f, labels=other)])
    with pytest.raises(LabelMismatch, match="wrong --profile or --rig"):
        list(src)


def test_unknown_labels_after_good_frames_are_only_counted(zmq_pair):
    from transport.badinput import MISMATCH_PACKETS

    pub, src = zmq_pair
    pub.send_multipart([TP, good(0)])
    other = [f"x{i}" for i in range(len(LABELS))]
    for f in range(1, MISMATCH_PACKETS + 5):
        pub.send_multipart([TP, good(f, labels=other)])
    assert [f.frame for f in src] == [0] and src.bad.counts["unknown_label"] == MISMATCH_PACKETS + 4
