"""Sinks in one process over real sockets: ZeroMQ (drops, header on join, CurveZMQ), VMC, Live Link Face."""

import socket
import time

import numpy as np
import pytest
import zmq
from hypothesis import given, settings
from hypothesis import strategies as st
from pythonosc.osc_bundle import OscBundle
from scipy.spatial.transform import Rotation

from livecap.core.result import SolveResult
from transport.arkit import ARKIT_NAMES, arkit_matrix, is_arkit
from transport.livelink import LiveLinkSink
from transport.security import Curve, keygen, udp_address, zmq_address
from transport.vmc import STANDARD_REST, VmcSink, to_unity
from transport.wire import decode_payload
from transport.zmq_sink import ZmqSink

NAMES = ["jawOpen", "eyeBlinkLeft", "mouthSmileRight", "cheekPuff"]


def result(frame=0, names=NAMES, w=None):
    w = np.linspace(0.1, 0.9, len(names)) if w is None else w
    return SolveResult(frame, frame / 120, names, w, Rotation.from_euler("YXZ", [0.2, -0.1, 0.05]).as_quat(),
                       np.array([10.0, -20.0, 30.0]), 0.1, 0.001)


def decode_livelink(pkt: bytes) -> dict:
    """Decoded by the PyLiveLinkFace package (PyPI pylivelinkface), not by livecap."""
    from pylivelinkface import PyLiveLinkFace

    ok, face = PyLiveLinkFace.decode(pkt)
    assert ok
    return dict(version=face._version, device=face.uuid, name=face.name, frame=face._frames, sub=face._sub_frame,
                fps=face.fps, den=face._denominator, count=len(face._blend_shapes), values=np.array(face._blend_shapes))


def neutral_then(res: SolveResult) -> SolveResult:
    """The neutral-pose frame a sink sees first (identity rotation, the same translation)."""
    return SolveResult(res.frame - 1, res.timestamp - 1 / 120, res.names, res.weights, np.array([0, 0, 0, 1.0]),
                       np.zeros(3), 0.1, 0.001)


def udp_listener():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(2)
    return s


def test_livelink_packet_decodes_with_published_layout():
    rx = udp_listener()
    sink = LiveLinkSink("127.0.0.1", rx.getsockname()[1], subject="anna", fps=120, timecode="10:00:00:00")
    sink.publish(neutral_then(result(42)))
    first = decode_livelink(rx.recv(4096))
    assert first["frame"] == 10 * 3600 * 120 and first["sub"] == 0  # frames since midnight at 120 fps
    sink.publish(result(42))
    d = decode_livelink(rx.recv(4096))
    assert d["version"] == 6 and d["device"] == first["device"] and d["device"].startswith("$")
    assert d["name"] == "anna" and d["frame"] == 10 * 3600 * 120 + 1 and d["fps"] == 120 and d["den"] == 1
    assert d["count"] == 61
    vals = d["values"]
    w = result().weights
    for name, wi in zip(NAMES, w, strict=True):
        assert vals[ARKIT_NAMES.index(name)] == pytest.approx(wi, abs=1e-6)
    assert vals[ARKIT_NAMES.index("tongueOut")] == 0
    np.testing.assert_allclose(vals[52:55], [0.2, -0.1, 0.05], atol=1e-6)  # head yaw, pitch, roll (rad)
    sink.close()


def test_ict_names_map_onto_arkit():
    ict = ["eyeBlink_L", "eyeBlink_R", "browInnerUp_L", "browInnerUp_R", "jawOpen", "mouthLeft", "mouthSmile_R"]
    M = arkit_matrix(ict)
    w = np.array([0.1, 0.2, 0.4, 0.8, 0.5, 0.3, 0.7])
    a = dict(zip(ARKIT_NAMES, M @ w, strict=True))
    assert a["eyeBlinkLeft"] == 0.1 and a["eyeBlinkRight"] == 0.2 and a["jawOpen"] == 0.5
    assert a["browInnerUp"] == pytest.approx(0.6) and a["mouthLeft"] == 0.3 and a["mouthSmileRight"] == 0.7
    assert a["mouthSmileLeft"] == 0
    M2 = arkit_matrix(ict, {"mouthSmileLeft": "mouthSmile_R", "browInnerUp": "browInnerUp_L"})
    a2 = dict(zip(ARKIT_NAMES, M2 @ w, strict=True))
    assert a2["mouthSmileLeft"] == 0.7 and a2["browInnerUp"] == 0.4
    with pytest.raises(ValueError, match="no shape"):
        arkit_matrix(ict, {"jawOpen": "jaw_drop"})
    assert is_arkit(NAMES) and not is_arkit(ict)


def test_ict_rig_names_map_fully(ict):
    rig, _ = ict
    M = arkit_matrix(rig.names)
    covered = M.sum(1) > 0
    assert covered.sum() >= 51  # everything but tongueOut, which ICT does not have
    assert np.allclose(M.sum(1)[covered], 1.0)


def test_vmc_bundle_per_frame_with_apply_last():
    rx = udp_listener()
    sink = VmcSink("127.0.0.1", rx.getsockname()[1])
    sink.publish(neutral_then(result(3)))
    rx.recv(65536)
    sink.publish(result(3))
    msgs = list(OscBundle(rx.recv(65536)))
    addrs = [m.address for m in msgs]
    assert addrs[-1] == "/VMC/Ext/Blend/Apply" and addrs.count("/VMC/Ext/Blend/Val") == len(NAMES)
    vals = {m.params[0]: m.params[1] for m in msgs if m.address == "/VMC/Ext/Blend/Val"}
    assert vals == pytest.approx(dict(zip(NAMES, result().weights, strict=True)), abs=1e-6)
    head = next(m for m in msgs if m.address == "/VMC/Ext/Bone/Pos").params
    assert head[0] == "Head"
    np.testing.assert_allclose(head[1:4], STANDARD_REST["Head"], atol=1e-7)  # rest offset; the shift is the root's
    root = next(m for m in msgs if m.address == "/VMC/Ext/Root/Pos").params
    np.testing.assert_allclose(root[1:4], [-0.010, -0.020, 0.030], atol=1e-7)


def test_vmc_splits_big_rigs_and_keeps_apply_last():
    names = [f"shape{i:03d}" for i in range(400)]
    sink = VmcSink("127.0.0.1", 9)
    dgrams = sink.datagrams(result(0, names, np.zeros(400)))
    assert len(dgrams) > 1 and all(len(d) <= 8192 for d in dgrams)
    msgs = [m for d in dgrams for m in OscBundle(d)]
    assert [m.address for m in msgs].count("/VMC/Ext/Blend/Val") == 400
    assert msgs[-1].address == "/VMC/Ext/Blend/Apply"


@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
       st.lists(st.floats(-100, 100), min_size=3, max_size=3), st.lists(st.floats(-100, 100), min_size=3,
                                                                        max_size=3))
@settings(max_examples=50, deadline=None)
def test_unity_conversion_is_the_x_mirror(q, t, v):
    """Mirroring x on both sides: rotate-then-translate in Unity == mirror of ours (in metres)."""
    q = np.array(q) / np.linalg.norm(q)
    v = np.array(v)
    ours = Rotation.from_quat(q).apply(v) + t
    p_u, q_u = to_unity(np.array(t), q)
    mirror = np.array([-1.0, 1, 1])
    theirs = Rotation.from_quat(q_u).apply(mirror * v / 1000) + p_u
    np.testing.assert_allclose(theirs, mirror * ours / 1000, atol=1e-9)


# ------------------------------------------------------------------------------- ZeroMQ
def test_zmq_sink_counts_drops_instead_of_blocking():
    ctx = zmq.Context()
    sink = ZmqSink("inproc://w", hwm=2, policy="count", context=ctx)
    stuck = ctx.socket(zmq.SUB)
    stuck.setsockopt(zmq.RCVHWM, 2)
    stuck.connect("inproc://w")
    stuck.setsockopt(zmq.SUBSCRIBE, b"weights.actor")
    time.sleep(0.05)
    for i in range(200):
        sink.publish(result(i))
    assert sink.drops > 150 and sink.sent + sink.drops == 200
    stuck.close(0)
    sink.close()
    ctx.term()


@pytest.mark.parametrize("policy", ["fair", None])  # None: the default must never let one reader starve another
def test_zmq_sink_fair_policy_keeps_feeding_a_reader_next_to_a_stuck_one(policy):
    ctx = zmq.Context()
    sink = ZmqSink("inproc://f", hwm=2, context=ctx, **({"policy": policy} if policy else {}))
    stuck, reader = ctx.socket(zmq.SUB), ctx.socket(zmq.SUB)
    for s in (stuck, reader):
        s.setsockopt(zmq.RCVHWM, 2)
        s.connect("inproc://f")
        s.setsockopt(zmq.SUBSCRIBE, b"weights.actor")
    time.sleep(0.05)
    got = []
    for i in range(100):
        sink.publish(result(i))
        while reader.poll(0):
            msg = decode_payload(reader.recv_multipart()[1])
            if not isinstance(msg, dict):
                got.append(msg.frame)
    assert got == list(range(100))
    for s in (stuck, reader):
        s.close(0)
    sink.close()
    ctx.term()


def test_header_sent_on_join_before_weights():
    ctx = zmq.Context()
    sink = ZmqSink("tcp://127.0.0.1:*", header_every=1e9, context=ctx)
    sink.publish(result(0))  # nobody listening yet
    sub = ctx.socket(zmq.SUB)
    sub.connect(sink.address)
    sub.setsockopt(zmq.SUBSCRIBE, b"weights.actor")
    time.sleep(0.3)
    sink.publish(result(1))
    first = decode_payload(sub.recv_multipart()[1])
    second = decode_payload(sub.recv_multipart()[1])
    assert first["type"] == "header" and first["names"] == NAMES
    assert second.frame == 1 and second.names_id == first["names_id"] and sink.joins == 1
    sub.close(0)
    sink.close()
    ctx.term()


def test_curve_lets_in_only_allowed_clients(tmp_path):
    keygen(tmp_path / "server", "server")
    keygen(tmp_path / "allowed", "client")
    keygen(tmp_path / "other", "intruder")
    ctx = zmq.Context()
    sink = ZmqSink("tcp://127.0.0.1:*", context=ctx, header_every=0,
                   curve=Curve(tmp_path / "server" / "server.key_secret", allowed=tmp_path / "allowed"))

    def client(secret):
        s = ctx.socket(zmq.SUB)
        Curve(secret, server_public=tmp_path / "server" / "server.key").apply(s, server=False)
        s.connect(sink.address)
        s.setsockopt(zmq.SUBSCRIBE, b"")
        return s

    good = client(tmp_path / "allowed" / "client.key_secret")
    bad = client(tmp_path / "other" / "intruder.key_secret")
    time.sleep(0.5)
    for i in range(5):
        sink.publish(result(i))
    assert good.poll(2000) and decode_payload(good.recv_multipart()[1])["type"] == "header"
    assert not bad.poll(300)
    for s in (good, bad):
        s.close(0)
    sink.close()
    from transport.security import stop_authenticators

    stop_authenticators()
    ctx.term()


def test_addresses_stay_on_loopback_unless_told():
    assert zmq_address("5555") == "tcp://127.0.0.1:5555"
    assert zmq_address("0") == "tcp://127.0.0.1:*"
    assert udp_address("9000", 1) == ("127.0.0.1", 9000)
    assert udp_address("localhost", 39539) == ("localhost", 39539)
    with pytest.raises(ValueError, match="--interface"):
        zmq_address("tcp://0.0.0.0:5555")
    with pytest.raises(ValueError, match="--interface"):
        udp_address("192.168.1.20:11111", 11111)
    assert zmq_address("tcp://0.0.0.0:5555", "0.0.0.0") == "tcp://0.0.0.0:5555"
    assert zmq_address("5555", "10.0.0.2") == "tcp://10.0.0.2:5555"
