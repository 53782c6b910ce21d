"""Wire formats: round trips, and hostile bytes only ever raise the typed, counted errors."""

import struct

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.core.result import SolveResult
from transport.badinput import BadInput, FrameOrder, LabelMap
from transport.osc_source import OscDecodeError, decode_osc_frame, encode_osc_frame
from transport.wire import (
    WIRE_VERSION,
    DuplicateLabel,
    MalformedPacket,
    NonFinite,
    ShortPacket,
    UnknownLayout,
    WireError,
    WrongVersion,
    decode_markers,
    decode_payload,
    encode_header,
    encode_markers,
    encode_weights,
    layout_id,
)

LABELS = [f"M{i:02d}" for i in range(8)]
coords = st.floats(-1e4, 1e4, allow_nan=False, width=32)


@st.composite
def frames(draw):
    n = draw(st.integers(1, 12))
    pos = np.array(draw(st.lists(coords, min_size=3 * n, max_size=3 * n)), dtype=np.float32).reshape(n, 3)
    valid = np.array(draw(st.lists(st.booleans(), min_size=n, max_size=n)))
    labels = [f"L{i}" for i in range(n)]
    return draw(st.integers(-(2**31), 2**31)), draw(st.floats(0, 1e6)), labels, pos, valid


@given(frames())
@settings(max_examples=60, deadline=None)
def test_markers_round_trip(f):
    frame, ts, labels, pos, valid = f
    pkt = decode_markers(encode_markers(frame, ts, pos, valid, labels))
    assert pkt.frame == frame and pkt.timestamp == ts and pkt.labels == labels
    np.testing.assert_array_equal(pkt.valid, valid)
    np.testing.assert_array_equal(pkt.positions[valid], pos[valid].astype(np.float64))
    assert not pkt.positions[~valid].any()


def test_layout_id_learnt_then_used():
    layouts = {}
    pos, val = np.zeros((8, 3)), np.ones(8, bool)
    lid = layout_id(LABELS)
    with pytest.raises(UnknownLayout):
        decode_markers(encode_markers(0, 0.0, pos, val, layout=lid), layouts)
    decode_markers(encode_markers(1, 0.0, pos, val, LABELS, lid), layouts)
    assert decode_markers(encode_markers(2, 0.0, pos, val, layout=lid), layouts).labels == LABELS


def _packet(**over):
    msg = {"v": WIRE_VERSION, "type": "markers", "frame": 3, "timestamp": 0.5, "labels": ["a", "b"],
           "positions": np.zeros(6, "<f4").tobytes(), "valid": b"\x01\x01"}
    msg.update(over)
    return msgpack.packb({k: v for k, v in msg.items() if v is not None}, use_bin_type=True)


@pytest.mark.parametrize("payload, error", [
    (b"", ShortPacket),
    (_packet()[:-3], ShortPacket),
    (b"\xc1\xc1garbage", MalformedPacket),
    (msgpack.packb([1, 2, 3]), MalformedPacket),
    (_packet(v=2), WrongVersion),
    (_packet(v=None), MalformedPacket),
    (_packet(labels=["a", "a"]), DuplicateLabel),
    (_packet(positions=np.zeros(5, "<f4").tobytes()), ShortPacket),
    (_packet(positions=np.zeros(7, "<f4").tobytes()), MalformedPacket),
    (_packet(positions=np.array([0, np.nan, 0, 0, 0, 0], "<f4").tobytes()), NonFinite),
    (_packet(timestamp=float("inf")), NonFinite),
    (_packet(valid=b"\x01"), ShortPacket),
    (_packet(frame="x"), MalformedPacket),
    (_packet(labels=None), MalformedPacket),
])
def test_bad_marker_packets_raise_their_kind(payload, error):
    with pytest.raises(error):
        decode_markers(payload, {})


def test_nan_on_a_missing_marker_is_fine():
    pos = np.array([[np.nan, 0, 0], [1, 2, 3]], "<f4")
    pkt = decode_markers(encode_markers(0, 0.0, pos, [False, True], ["a", "b"]))
    assert np.isfinite(pkt.positions).all() and pkt.valid.tolist() == [False, True]


@given(st.binary(max_size=400))
@settings(max_examples=300, deadline=None)
def test_random_bytes_only_raise_wire_errors(data):
    try:
        decode_markers(data, {})
    except WireError:
        pass


@given(st.data())
@settings(max_examples=200, deadline=None)
def test_mutated_packets_only_raise_wire_errors(data):
    good = bytearray(encode_markers(7, 1.0, np.ones((8, 3)), np.ones(8, bool), LABELS))
    for _ in range(data.draw(st.integers(1, 6))):
        i = data.draw(st.integers(0, len(good) - 1))
        good[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(good)))
    try:
        pkt = decode_markers(bytes(good[:cut]), {})
    except WireError:
        return
    assert np.isfinite(pkt.positions).all()


def test_weights_and_header_round_trip():
    names = ["jawOpen", "eyeBlinkLeft", "x"]
    res = SolveResult(12, 0.1, names, np.array([0.1, 0.5, 1.0]), np.array([0, 0, 0.6, 0.8]),
                      np.array([1.0, 2.0, 3.0]), 0.25, 0.001)
    head = decode_payload(encode_header(names, "anna", 120))
    assert head["names"] == names and head["actor"] == "anna" and head["names_id"] == layout_id(names)
    pkt = decode_payload(encode_weights(res, head["names_id"]))
    assert pkt.frame == 12 and pkt.names_id == head["names_id"]
    np.testing.assert_allclose(pkt.weights, res.weights, atol=1e-7)
    np.testing.assert_array_equal(pkt.head_rotation, res.head_rotation)
    np.testing.assert_array_equal(pkt.head_translation, res.head_translation)


# ------------------------------------------------------------------------------------- OSC
WHERE = {lab: i for i, lab in enumerate(LABELS)}


@given(frames())
@settings(max_examples=40, deadline=None)
def test_osc_round_trip(f):
    frame, ts, _, pos, valid = f
    n = min(len(pos), len(LABELS))
    frame = int(np.clip(frame, -(2**31), 2**31 - 1))
    d = encode_osc_frame(frame, ts, LABELS[:n], pos[:n], valid[:n])
    fr, t, p, v = decode_osc_frame(d, WHERE)
    assert fr == frame and t == ts
    np.testing.assert_array_equal(v[:n], valid[:n])
    np.testing.assert_allclose(p[:n][valid[:n]], pos[:n][valid[:n]], rtol=1e-6)


@pytest.mark.parametrize("make, kind", [
    (lambda: b"#bundle\0" + b"\0" * 4, "short"),
    (lambda: b"/livecap/frame\0\0,iidi\0\0\0" + b"\0" * 20, "malformed"),  # a message, not a bundle
    (lambda: encode_osc_frame(1, 0.0, ["M00", "M00"], np.zeros((2, 3)), [True, True]), "duplicate_label"),
    (lambda: encode_osc_frame(1, 0.0, ["nope"], np.zeros((1, 3)), [True]), "unknown_label"),
    (lambda: encode_osc_frame(1, 0.0, ["M00"], np.array([[np.inf, 0, 0]]), [True]), "nonfinite"),
    (lambda: _osc_with_version(2), "version"),
    (lambda: _osc_truncated_count(), "short"),
])
def test_bad_osc_bundles_raise_their_kind(make, kind):
    with pytest.raises(OscDecodeError) as err:
        decode_osc_frame(make(), WHERE)
    assert err.value.kind == kind


def _osc_with_version(v):
    d = bytearray(encode_osc_frame(1, 0.0, ["M00"], np.zeros((1, 3)), [True]))
    at = d.index(b",iidi") + 8
    d[at:at + 4] = struct.pack(">i", v)
    return bytes(d)


def _osc_truncated_count():
    d = bytearray(encode_osc_frame(1, 0.0, ["M00"], np.zeros((1, 3)), [True]))
    at = d.index(b",iidi") + 8 + 16
    d[at:at + 4] = struct.pack(">i", 2)  # says 2 markers, carries 1
    return bytes(d)


@given(st.binary(max_size=300))
@settings(max_examples=300, deadline=None)
def test_random_bytes_at_osc_decoder(data):
    try:
        decode_osc_frame(data, WHERE)
    except OscDecodeError:
        pass


@given(st.data())
@settings(max_examples=200, deadline=None)
def test_mutated_osc_bundles(data):
    good = bytearray(encode_osc_frame(7, 1.0, LABELS, np.ones((8, 3)), np.ones(8, bool)))
    for _ in range(data.draw(st.integers(1, 6))):
        good[data.draw(st.integers(0, len(good) - 1))] = data.draw(st.integers(0, 255))
    try:
        _, _, p, _ = decode_osc_frame(bytes(good[: data.draw(st.integers(0, len(good)))]), WHERE)
    except OscDecodeError:
        return
    assert np.isfinite(p).all()


# --------------------------------------------------------------------------- stream checks
def test_frame_order_counts_duplicates_and_out_of_order():
    order = FrameOrder()
    assert [order.check(f) for f in [1, 2, 2, 1, 5, 3, 6]] == [None, None, "duplicate_frame", "out_of_order", None,
                                                                "out_of_order", None]


def test_frame_order_a_restarted_sender_is_a_new_stream():
    order = FrameOrder()
    assert all(order.check(f, f / 120) is None for f in range(1000, 1400))
    assert order.check(0, 0.0) is None and order.restarts == 1  # solving resumes at once
    assert [order.check(f, f / 120) for f in (1, 2, 3)] == [None, None, None]


def test_frame_order_a_timestamp_jump_back_is_a_new_stream():
    order = FrameOrder()
    assert order.check(100, 50.0) is None and order.check(101, 50.01) is None
    assert order.check(95, 1.0) is None and order.restarts == 1  # frame only 6 back, but time ran back 49 s


def test_frame_order_one_lying_frame_number_is_ignored_not_adopted():
    order = FrameOrder()
    assert order.check(10) is None
    assert order.check(2**40) == "frame_outlier"
    assert [order.check(f) for f in range(11, 20)] == [None] * 9 and order.restarts == 0
    # a real jump (the next frame continues from it) is adopted on its second frame
    assert order.check(10**6) == "frame_outlier" and order.check(10**6 + 1) is None and order.last == 10**6 + 1


def test_label_map_reorders_and_rejects_unknown():
    m = LabelMap(["a", "b", "c"])
    f = m.frame(0, 0.0, ["c", "a"], np.array([[3, 3, 3], [1, 1, 1.0]]), np.array([True, True]))
    assert f.valid.tolist() == [True, False, True] and f.positions[2, 0] == 3 and f.positions[0, 0] == 1
    with pytest.raises(KeyError):
        m.index(["a", "zz"])


def test_bad_input_log_is_rate_limited(caplog):
    bad = BadInput("test", interval=60)
    with caplog.at_level("WARNING"):
        for _ in range(50):
            bad.skip("short", "x")
    assert bad.counts["short"] == 50 and len(caplog.records) == 1
