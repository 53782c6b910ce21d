"""The iPhone as a source (issue 40): the real Live Link Face packets in
../shared/realdata/performance/dao.gesichter decoded, replayed over loopback at their own rate into
``livecap run --livelink-in`` and read back from VMC (python-osc) and ZeroMQ (pyzmq + msgpack,
docs/protocol.md) as a receiver would."""

from __future__ import annotations

import csv
import re
import socket
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pylivelinkface import FaceBlendShape, PyLiveLinkFace
from pythonosc.osc_bundle import OscBundle
from scipy.spatial.transform import Rotation

from benchmarks.iphone_latency import PACKETS
from benchmarks.iphone_latency import real_packets as llv_packets
from livecap.core.eyes import EYE_PITCH, EYE_YAW, eye_angles
from livecap.core.headpose import NeutralPose
from livecap.core.result import SolveResult
from tests.conftest import ICT, ROOT, SHARED
from transport.arkit import POSE_NAMES, head_angles
from transport.livelink import LiveLinkSink, encode_livelink
from transport.livelink_source import LiveLinkFaceSource, decode_livelink, head_quaternion
from transport.recorders import CsvRecorder
from transport.vmc import PERFECT_SYNC_NAMES, VmcSink

MAP = ROOT / "examples" / "makehuman_arkit.json"


def real_packets() -> list[bytes]:
    """The LLV recording's packets (every byte accounted for: benchmarks.iphone_latency.real_packets)."""
    if not PACKETS.exists():
        pytest.skip(f"{PACKETS} not present (real Live Link Face packets, ../shared/realdata)")
    return llv_packets()


def test_real_packets_decode_with_their_angles():
    pkts = [decode_livelink(p) for p in real_packets()]
    assert len(pkts) == 180
    assert {p.fps for p in pkts} == {60} and {p.denominator for p in pkts} == {1}
    assert len(pkts[0].device) == 32  # not a 36-byte UUID: read by its length prefix
    frames = np.array([p.frame for p in pkts])
    assert (np.diff(frames) > 0).all()
    V = np.stack([p.values for p in pkts])
    assert 0 <= V[:, :52].min() and V[:, :52].max() <= 1 and V[:, :52].max() > 0.3
    assert np.abs(V[:, 52:55]).max() > 0.05  # the head turns
    assert np.abs(V[:, [55, 58]]).max() > 0.05  # and the eyes (LeftEyeYaw, RightEyeYaw)


def test_what_livecap_and_pylivelinkface_encode_decodes():
    rng = np.random.default_rng(3)
    vals = rng.uniform(-1, 1, 61).astype(np.float32)
    p = decode_livelink(encode_livelink(vals, 1234, "Face", None, 30000, 1001, 0.25))
    assert p.frame == 1234 and p.subject == "Face" and (p.fps, p.denominator) == (30000, 1001)
    assert np.array_equal(p.values, vals.astype(float)) and p.sub_frame == 0.25
    face = PyLiveLinkFace(name="phone", fps=60)
    for i in range(61):
        face._blend_shapes[i] = float(vals[i])
    third = decode_livelink(face.encode())
    assert third.subject == "phone" and np.allclose(third.values, vals, atol=1e-7)


def test_head_quaternion_inverts_head_angles():
    ang = np.array([0.4, -0.3, 0.2])
    assert np.allclose(head_angles(head_quaternion(ang)), ang)


def _send(sock, port, dgram):
    sock.sendto(dgram, ("127.0.0.1", port))


def test_bad_packets_are_counted_and_a_new_device_is_followed():
    pkts = real_packets()
    src = LiveLinkFaceSource("127.0.0.1", 0, idle_timeout=0.5)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other = bytearray(pkts[0])
    other[5:9] = b"FEED"  # another phone: a different device id, its frame numbers start over
    bad = [pkts[0][:40], b"\x05" + pkts[0][1:], pkts[0] + b"\0\0\0\0", b"garbage" * 10,
           pkts[0][:-4] + struct.pack(">f", float("nan"))]
    try:
        for d in [pkts[0], *bad, pkts[1], pkts[1], bytes(other)]:
            _send(tx, src.port, d)
        got = list(src)
    finally:
        tx.close()
        src.close()
    assert [r.frame for r in got] == [decode_livelink(p).frame for p in (pkts[0], pkts[1], bytes(other))]
    c = src.bad.as_dict()
    assert c["short"] == 2 and c["version"] == 1 and c["malformed"] == 1 and c["nonfinite"] == 1
    assert c["duplicate_frame"] == 1 and c["stream_restart"] == 1
    assert src.device == decode_livelink(bytes(other)).device


@pytest.fixture(scope="module")
def session():
    """The 180 real packets at 60 Hz into a real ``livecap run --livelink-in`` with VMC and ZeroMQ out."""
    return run_session(["--vmc-perfect-sync"])


def run_session(extra: list[str]):
    """``livecap run --livelink-in`` with ``extra`` flags, fed the real packets at their rate: (packets,
    ZeroMQ weight messages, VMC bundles, the report)."""
    import msgpack
    import zmq

    pkts = real_packets()
    vmc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vmc.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    vmc.bind(("127.0.0.1", 0))
    vmc.settimeout(0.5)
    cmd = [sys.executable, "-m", "livecap", "run", "--livelink-in", "127.0.0.1:0", "--vmc",
           f"127.0.0.1:{vmc.getsockname()[1]}", *extra, "--zmq-out", "tcp://127.0.0.1:*",
           "--idle-timeout", "1.5", "--first-frame-timeout", "30"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        ready = proc.stdout.readline()
        assert ready.startswith("ready:"), proc.stderr.read()
        port = int(re.search(r"livelink-in [\d.]+:(\d+)", ready).group(1))
        sub.connect(re.search(r"zmq-out ([^;\s]+)", ready).group(1))
        sub.setsockopt(zmq.SUBSCRIBE, b"weights.")
        sub.setsockopt(zmq.RCVTIMEO, 5000)
        time.sleep(0.5)  # the subscription reaches the publisher
        t0 = time.perf_counter()
        for k, p in enumerate(pkts):  # the app's own rate: 60 packets a second
            time.sleep(max(0.0, t0 + k / 60.0 - time.perf_counter()))
            tx.sendto(p, ("127.0.0.1", port))
        zmq_frames = []
        while len(zmq_frames) < len(pkts):
            try:
                _, payload = sub.recv_multipart()
            except zmq.Again:
                break
            msg = msgpack.unpackb(payload, raw=False)
            if msg["type"] == "weights":
                zmq_frames.append(msg)
        out, err = proc.communicate(timeout=60)
        bundles = []
        while True:
            try:
                bundles.append(vmc.recv(65536))
            except TimeoutError:
                break
    finally:
        tx.close()
        vmc.close()
        sub.close(0)
        ctx.term()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    return [decode_livelink(p) for p in pkts], zmq_frames, bundles, out


def test_zmq_carries_every_packet_weight_and_head_rotation(session):
    pkts, frames, _, _ = session
    assert [m["frame"] for m in frames] == [p.frame for p in pkts]
    for m, p in zip(frames, pkts, strict=True):
        assert np.array_equal(np.frombuffer(m["weights"], "<f4"), p.values[:52].astype(np.float32))
        assert np.allclose(head_angles(np.array(m["head_rotation"])), p.values[52:55], atol=1e-6)
        assert m["timestamp"] == pytest.approx(p.seconds)


def test_vmc_perfect_sync_carries_every_packet_weight_and_head_rotation(session):
    pkts, _, bundles, out = session
    assert len(bundles) == len(pkts), out
    for dgram, p in zip(bundles, pkts, strict=True):
        msgs = list(OscBundle(dgram))
        vals = {m.params[0]: m.params[1] for m in msgs if m.address == "/VMC/Ext/Blend/Val"}
        assert list(vals) == PERFECT_SYNC_NAMES
        assert np.array_equal(np.array(list(vals.values()), np.float32), p.values[:52].astype(np.float32))
        head = next(m.params for m in msgs if m.address == "/VMC/Ext/Bone/Pos" and m.params[0] == "Head")
        q = np.array(head[4:8])
        q[1:3] *= -1  # Unity's left-handed axes back to the rig's (livecap.core.headpose.to_unity)
        assert np.allclose(head_angles(q), p.values[52:55], atol=1e-5)
    assert "frames in 180, out 180" in out and "bad input: none" in out


LOOKING = ["eyeLookOutLeft", "eyeLookInRight", "eyeLookDownLeft", "eyeLookDownRight", "jawOpen"]


def _looking(w=(1.0, 1.0, 0.5, 0.5, 0.3), t=0.0):
    return SolveResult(0, t, LOOKING, np.array(w), np.array([0, 0, 0, 1.0]), np.zeros(3))


def test_livelink_packets_carry_eye_angles_from_the_look_shapes():
    """Issue 37.6: eye yaw/pitch as the app sends them (both eyes to the subject's left, down), read
    by PyLiveLinkFace; the same function drives the VMC eye bones."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2)
    sink = LiveLinkSink("127.0.0.1", rx.getsockname()[1])
    try:
        sink.publish(_looking())
        ok, face = PyLiveLinkFace.decode(rx.recv(4096))
    finally:
        sink.close()
        rx.close()
    assert ok
    got = [face.get_blendshape(FaceBlendShape[n]) for n in POSE_NAMES[3:]]
    assert np.allclose(got, [-EYE_YAW, 0.5 * EYE_PITCH, 0, -EYE_YAW, 0.5 * EYE_PITCH, 0], atol=1e-6)
    vmc = VmcSink("127.0.0.1", 9, names="perfect-sync")
    bones = {m.params[0]: m.params[4:] for d in vmc.datagrams(_looking()) for m in OscBundle(d)
             if m.address == "/VMC/Ext/Bone/Pos"}
    vmc.close()
    yaw_pitch = Rotation.from_quat(bones["LeftEye"]).as_euler("YXZ")[:2]
    assert np.allclose(yaw_pitch, [-EYE_YAW, 0.5 * EYE_PITCH], atol=1e-6)


def test_llf_csv_carries_eye_angles_and_one_row_per_timecode_frame(tmp_path):
    """Issues 37.6 and 37.3: a 120 Hz stream recorded in the app's layout keeps one row per 60 fps
    timecode frame (the first), read by a reader that keys rows by frame; eye angles as the app's."""
    path = tmp_path / "w.csv"
    rec = CsvRecorder(path, rate=120.0, layout="livelinkface", timecode="01:00:00:00")
    for k in range(240):
        rec.publish(_looking(w=(1.0, 1.0, 0.5, 0.5, k / 240), t=k / 120))
    rec.close()
    rows = list(csv.reader(open(path)))
    header, body = rows[0], rows[1:]
    by_frame = {r[0][:11]: r for r in body}
    assert len(by_frame) == len(body) == 120 and rec.merged == 120
    assert [r[0] for r in body[:2]] == ["01:00:00:00.000", "01:00:00:01.000"]
    row = dict(zip(header, body[0], strict=True))
    assert float(row["LeftEyeYaw"]) == pytest.approx(-EYE_YAW) and float(row["RightEyeYaw"]) == pytest.approx(-EYE_YAW)
    assert float(row["LeftEyePitch"]) == pytest.approx(0.5 * EYE_PITCH)
    assert float(body[1][header.index("JawOpen")]) == pytest.approx(2 / 240)  # the frame's first result


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1.4, 1.4), min_size=3, max_size=3), st.lists(st.floats(-1, 1), min_size=4, max_size=4))
def test_closed_form_rotations_agree_with_scipy(angles, q0):
    """head_quaternion / head_angles / NeutralPose.relative skip scipy per frame; same results."""
    ang = np.array(angles)
    q = head_quaternion(ang)
    assert np.allclose(np.abs(q @ Rotation.from_euler("YXZ", ang).as_quat()), 1.0, atol=1e-9)
    assert np.allclose(head_angles(q), Rotation.from_quat(q).as_euler("YXZ"), atol=1e-7)
    if np.linalg.norm(q0) > 0.1:
        pose = NeutralPose(Rotation.from_quat(q0).as_matrix(), np.zeros(3))
        fast, _ = pose.relative(q, np.zeros(3))
        slow, _ = pose.relative(q[None], np.zeros((1, 3)))
        assert np.allclose(np.abs(fast @ slow[0]), 1.0, atol=1e-9)
    still = NeutralPose(np.eye(3), np.zeros(3))  # the iPhone's: its floats-only path against scipy's
    fast, shift = still.relative(3 * q, np.array(angles) * 100)
    slow, shift_slow = still.relative(q[None], np.array(angles)[None] * 100)
    assert np.allclose(np.abs(fast @ slow[0]), 1.0, atol=1e-9) and np.allclose(shift, shift_slow[0])
    looks = np.abs(np.concatenate([q0, q0[::-1]])).reshape(2, 4)
    by_numpy = np.stack([EYE_YAW * np.array([-1.0, 1.0]) * (looks[:, 0] - looks[:, 1]),
                         EYE_PITCH * (looks[:, 2] - looks[:, 3])], axis=1)
    assert np.allclose(eye_angles(looks), by_numpy)


MH = SHARED / "realdata" / "makehuman-head"


@pytest.fixture(scope="module", params=["map", "transfer"])
def makehuman(request):
    """The same packets retargeted onto the MakeHuman head (no ARKit names) by the mapping file and by
    expression transfer through the ICT face; what each frame must carry, computed here in-process."""
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.retarget import ByName, ExpressionTransfer
    from transport.arkit import load_mapping

    if not (MH / "neutral.obj").exists() or not (ICT / "neutral.obj").exists():
        pytest.skip(f"MakeHuman head or ICT rig absent under {SHARED / 'realdata'}")
    mh = Rig.load(MH)
    how = ["--map", str(MAP)] if request.param == "map" else ["--transfer", str(ICT)]
    if request.param == "map":
        expected = ByName(mh, load_mapping(MAP))
    else:
        ict = Rig.load(ICT)
        expected = ExpressionTransfer(ict, MarkerLayout.load(ICT / "markers.json", ict), mh)
    pkts, frames, bundles, out = run_session(["--rig", str(MH), *how])
    want = [np.array(expected.step(p.values[:52]), dtype=float) for p in pkts]
    return request.param, mh.names, pkts, want, frames, bundles, out


def test_makehuman_gets_the_retargeted_weights_and_the_packet_head_on_zmq_and_vmc(makehuman):
    how, names, pkts, want, frames, bundles, out = makehuman
    assert [m["frame"] for m in frames] == [p.frame for p in pkts], out
    assert len(bundles) == len(pkts) and "bad input: none" in out
    tol = 0 if how == "map" else 1e-5  # the map is one exact matrix; the transfer's QP agrees to float32
    for m, dgram, p, w in zip(frames, bundles, pkts, want, strict=True):
        assert np.allclose(np.frombuffer(m["weights"], "<f4"), w.astype(np.float32), rtol=0, atol=tol)
        assert np.allclose(head_angles(np.array(m["head_rotation"])), p.values[52:55], atol=1e-6)
        msgs = list(OscBundle(dgram))
        vals = {x.params[0]: x.params[1] for x in msgs if x.address == "/VMC/Ext/Blend/Val"}
        assert list(vals) == names
        assert np.allclose(np.array(list(vals.values()), np.float32), w.astype(np.float32), rtol=0, atol=tol)
    assert np.abs(np.stack(want)).max() > 0.2  # the face moves


def test_the_relay_loop_runs_with_one_blas_thread_and_a_frozen_heap():
    """What the packet -> weights p99 needed (docs/iphone.md, Latency): no OpenBLAS thread wake-ups, no full
    collection walking the start-up's objects; both undone when the session ends."""
    import gc

    from threadpoolctl import threadpool_info

    from livecap.live.relay import WeightsPipeline

    seen = {}

    def source():
        seen["blas"] = {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}
        seen["frozen"] = gc.get_freeze_count()
        yield from ()

    WeightsPipeline(source(), []).run()
    assert seen["blas"] == {1} and seen["frozen"] > 1000
    assert gc.get_freeze_count() == 0


class _Keep:
    def __init__(self):
        self.got = []

    def publish(self, result):
        self.got.append((result.frame, result.weights.copy(), result.head_rotation.copy()))

    def close(self):
        pass


def _ramp(n=40, noise=0.0):
    rng = np.random.default_rng(2)
    names = ["jawOpen", "eyeBlinkLeft"]
    return [SolveResult(k, k / 60, names, np.array([0.01 * k, 0.5]) + rng.normal(0, noise, 2),
                        head_quaternion([0.01 * k, 0.0, 0.0]), np.zeros(3)) for k in range(n)]


def test_fixed_lag_smoothing_publishes_each_frame_lag_late_exact_on_a_ramp():
    from livecap.live.relay import WeightsPipeline

    sink = _Keep()
    WeightsPipeline(iter(_ramp()), [sink], smooth="3", rate=60.0).run()
    assert [f for f, _, _ in sink.got] == list(range(37))  # the last 3 are still in the window at the end
    for f, w, q in sink.got[3:]:
        assert np.allclose(w, [0.01 * f, 0.5]) and np.allclose(head_angles(q), [0.01 * f, 0, 0], atol=1e-4)


def test_one_euro_smoothing_quietens_still_weights_without_delaying_frames():
    from livecap.live.relay import WeightsPipeline

    frames = _ramp(200, noise=0.02)
    raw = np.array([r.weights[1] for r in frames])
    sink = _Keep()
    WeightsPipeline(iter(frames), [sink], smooth="1e", rate=60.0).run()
    assert [f for f, _, _ in sink.got] == list(range(200))
    out = np.array([w[1] for _, w, _ in sink.got])
    assert np.std(out[50:]) < 0.7 * np.std(raw[50:])  # 0.53 x measured: beta 30 opens the cutoff on jitter


def _numpy_calls(fn) -> int:
    """How many numpy functions and array methods ``fn()`` calls (C calls seen by the profiler)."""
    seen = [0]

    def hook(frame, event, arg):
        if event == "c_call":
            owner = getattr(arg, "__self__", None)
            module = getattr(arg, "__module__", None) or type(owner).__module__
            seen[0] += str(module).startswith("numpy")

    sys.setprofile(hook)
    try:
        fn()
    finally:
        sys.setprofile(None)
    return seen[0]


def test_the_live_link_pass_through_makes_few_numpy_calls_per_packet():
    """Packet in -> Live Link packet out with ARKit names. On a process woken by each packet (60 Hz) every
    numpy call costs ~10-30 us, ~10-100x its warm cost (docs/iphone.md, Latency): the path decodes, timestamps and
    encodes in Python floats (30 numpy calls per packet before, 2026-12-04)."""
    from livecap.live.relay import WeightsPipeline

    pkts = real_packets()[:20]
    src = LiveLinkFaceSource("127.0.0.1", 0)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    sink = LiveLinkSink("127.0.0.1", rx.getsockname()[1], timecode="take")
    pipe = WeightsPipeline(iter(()), [sink], rate=60.0)
    try:
        pipe.publish(src.decode(pkts[0]))  # the first packet builds the sink's name matrix
        counts = [_numpy_calls(lambda p=p: (pipe.timing["receive"].add(1e-5), pipe.publish(src.decode(p))))
                  for p in pkts[1:]]
    finally:
        src.close()
        sink.close()
        rx.close()
    assert sink.sent == len(pkts) and max(counts) <= 5, counts


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(0, 1), min_size=52, max_size=52), st.lists(st.floats(-1, 1), min_size=4, max_size=4))
def test_the_live_link_sink_in_floats_writes_what_numpy_wrote(weights, q0):
    """The sink's values and packet, built in Python floats, against scipy's angles and numpy's float32 bytes."""
    from transport.arkit import ARKIT_NAMES
    from transport.livelink import device_id

    if np.linalg.norm(q0) < 0.1:
        return
    sink = LiveLinkSink("127.0.0.1", 9, timecode="take")
    sink.close()
    sink.neutral.fix(NeutralPose(np.eye(3), np.zeros(3)))  # the iPhone's: angles already relative
    got = sink.values(SolveResult(7, 7 / 60, list(ARKIT_NAMES), np.array(weights), np.array(q0), np.zeros(3)))
    want = np.zeros(61)
    want[:52] = weights
    want[52:55] = Rotation.from_quat(q0).as_euler("YXZ")
    look = {n: w for n, w in zip(ARKIT_NAMES, weights, strict=True)}
    for at, side, out in ((55, "Left", -1.0), (58, "Right", 1.0)):
        want[at] = out * EYE_YAW * (look[f"eyeLookOut{side}"] - look[f"eyeLookIn{side}"])
        want[at + 1] = EYE_PITCH * (look[f"eyeLookDown{side}"] - look[f"eyeLookUp{side}"])
    diff = got - want
    diff[52:55] = (diff[52:55] + np.pi) % (2 * np.pi) - np.pi  # a roll of pi is also one of -pi
    assert np.allclose(diff, 0.0, atol=1e-7)
    dev = device_id("a")
    packed = (struct.pack("<I", 6) + dev.encode() + struct.pack(">i", 4) + b"Face"
              + struct.pack(">ifiiB", 7, 0.25, 60, 1, 61) + np.asarray(got, ">f4").tobytes())
    assert encode_livelink(got, 7, "Face", dev, 60, 1, 0.25) == packed


def test_the_source_waits_in_recv_with_the_kernels_timeout():
    """A blocking socket with SO_RCVTIMEO: Python's settimeout would poll before each recv (a system call per
    packet on the latency path); the idle timeout still ends the session."""
    src = LiveLinkFaceSource("127.0.0.1", 0, idle_timeout=0.3, poll_s=0.25)
    try:
        assert src.sock.gettimeout() is None
        sec, usec = struct.unpack("ll", src.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, 16))
        assert sec == 0 and abs(usec - 250000) < 10000  # the kernel rounds to its clock tick
        t0 = time.monotonic()
        assert list(src) == [] and time.monotonic() - t0 < 2.0
    finally:
        src.close()


def test_the_packet_cost_benchmark_runs_the_real_path():
    """benchmarks/iphone_packet_cost swaps the source's and the sink's sockets: it must still drive the real loop."""
    from benchmarks.iphone_packet_cost import measure

    real_packets()
    got = measure(40, 0.0)
    assert got["packets"] == 40 and 0 < got["p50_us"] <= got["p99_us"] < 1e5
