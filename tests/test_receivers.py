"""What receivers do with a real ``livecap run`` process's output, decoded by third-party code:
python-osc for VMC (checked against the VMC spec's addresses and types), PyLiveLinkFace (PyPI
pylivelinkface) for Live Link Face UDP, a real Live Link Face app CSV for the CSV layout (issue 16)."""

from __future__ import annotations

import re
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pylivelinkface import PyLiveLinkFace
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_server import ThreadingOSCUDPServer
from scipy.spatial.transform import Rotation

from livecap.core.headpose import NeutralWindow
from livecap.core.result import SolveResult
from livecap.core.timecode import frame_rate_fraction, now_of_day
from tests.conftest import ROOT, SHARED
from transport.livelink import LiveLinkSink, device_id, encode_livelink
from transport.vmc import STANDARD_REST, VmcSink

TAKE = ROOT / "recordings" / "demo_take.c3d"
RIG = ROOT / "recordings" / "demo_rig.npz"
APP_CSVS = SHARED / "realdata" / "performance"

# The VMC spec's (protocol.vmc.info, performer -> marionette) addresses and OSC type tags we send.
VMC_TYPES = {"/VMC/Ext/OK": "i", "/VMC/Ext/T": "f", "/VMC/Ext/Root/Pos": "sfffffff", "/VMC/Ext/Bone/Pos": "sfffffff",
             "/VMC/Ext/Blend/Val": "sf", "/VMC/Ext/Blend/Apply": ""}
# HumanBodyBones names a VMC receiver maps bones by.
VMC_BONES = {"Head", "LeftEye", "RightEye"}
VRM0 = {"A", "I", "U", "E", "O", "Blink", "Blink_L", "Blink_R", "Joy", "Angry", "Sorrow", "Fun"}
VRM1 = {"aa", "ih", "ou", "ee", "oh", "blink", "blinkLeft", "blinkRight", "happy", "angry", "sad", "relaxed",
        "surprised"}


def run_livecap(*args, timeout: float = 120) -> str:
    cmd = [sys.executable, "-m", "livecap", "run", "--replay", str(TAKE), "--rig", str(RIG), *map(str, args)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr
    return done.stdout


class OscReceiver:
    """A python-osc server in a thread: every message's address and decoded arguments."""

    def __init__(self) -> None:
        self.messages: list[tuple[str, tuple]] = []
        d = Dispatcher()
        d.set_default_handler(lambda addr, *args: self.messages.append((addr, args)))
        self.server = ThreadingOSCUDPServer(("127.0.0.1", 0), d)
        self.server.socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        time.sleep(0.3)
        self.server.shutdown()
        self.server.server_close()


def check_vmc_spec(messages) -> None:
    for addr, args in messages:
        assert addr in VMC_TYPES, addr
        tags = "".join({str: "s", float: "f", int: "i"}[type(a)] for a in args)
        assert tags == VMC_TYPES[addr], (addr, args)
        if addr == "/VMC/Ext/Bone/Pos":
            assert args[0] in VMC_BONES
        if addr == "/VMC/Ext/Root/Pos":
            assert args[0] == "root" and args[4:] == (0.0, 0.0, 0.0, 1.0)  # translation only


@pytest.fixture(scope="module")
def vmc_runs():
    """Three real sessions on the demo take: Perfect Sync, VRM 0.x, VRM 1.0 names."""
    out = {}
    for flag in (["--vmc-perfect-sync"], ["--vmc-vrm", "0"], ["--vmc-vrm", "1"]):
        rx = OscReceiver()
        try:
            run_livecap("--vmc", f"127.0.0.1:{rx.port}", *flag, "--max-frames", 360, "--speed", 2)
        finally:
            rx.close()
        out[flag[-1]] = rx.messages
    return out


def test_vmc_perfect_sync_names_and_head_on_its_neck(vmc_runs):
    msgs = vmc_runs["--vmc-perfect-sync"]
    check_vmc_spec(msgs)
    names = Counter(args[0] for addr, args in msgs if addr == "/VMC/Ext/Blend/Val")
    assert len(names) == 52 and "EyeBlinkLeft" in names and "JawOpen" in names
    assert all(n[0].isupper() for n in names)  # Perfect Sync clip names, as exact-match receivers want
    heads = np.array([args[1:] for addr, args in msgs if addr == "/VMC/Ext/Bone/Pos" and args[0] == "Head"])
    assert len(heads) > 300
    # the bone's local position is its rest offset from the Neck in every frame (EVMC4U applies it
    # as localPosition); the head's sway moves the model root instead
    np.testing.assert_allclose(heads[:, :3], np.tile(STANDARD_REST["Head"], (len(heads), 1)), atol=1e-7)
    roots = np.array([args[1:4] for addr, args in msgs if addr == "/VMC/Ext/Root/Pos"])
    assert len(roots) == len(heads)
    shift = np.linalg.norm(roots, axis=1)
    assert 0.001 < shift.max() < 0.05, f"head shift up to {shift.max():.3f} m"
    turn = np.degrees(Rotation.from_quat(heads[:, 3:]).magnitude())
    assert np.median(turn) < 15 and turn.max() < 45  # relative to the neutral, not the capture's axes


@pytest.mark.parametrize("version, expected", [("0", VRM0), ("1", VRM1)])
def test_vmc_vrm_presets(vmc_runs, version, expected):
    msgs = vmc_runs[version]
    check_vmc_spec(msgs)
    vals: dict[str, list[float]] = {}
    for addr, args in msgs:
        if addr == "/VMC/Ext/Blend/Val":
            vals.setdefault(args[0], []).append(args[1])
    assert set(vals) == expected
    allv = np.concatenate([np.array(v) for v in vals.values()])
    assert allv.min() >= 0 and allv.max() <= 1
    # the table's first row: the open-mouth viseme is the jaw, frame for frame (same take, same solve)
    jaw = [args[1] for addr, args in vmc_runs["--vmc-perfect-sync"] if addr == "/VMC/Ext/Blend/Val"
           and args[0] == "JawOpen"]
    # (as multisets: the threading OSC server may hand datagrams over out of order)
    np.testing.assert_allclose(np.sort(vals["A" if version == "0" else "aa"]), np.sort(np.clip(jaw, 0, 1)), atol=1e-6)
    assert max(np.ptp(v) for v in vals.values()) > 0.1


def test_vmc_eye_bones_from_eye_look_shapes():
    names = ["eyeLookOutLeft", "eyeLookInRight", "eyeLookUpLeft", "jawOpen"]
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2)
    sink = VmcSink("127.0.0.1", rx.getsockname()[1], names="perfect-sync")
    sink.publish(SolveResult(0, 0.0, names, np.array([1.0, 1.0, 0.0, 0.2]), np.array([0, 0, 0, 1.0]), np.zeros(3)))
    bones = {m.params[0]: m.params[1:] for m in OscBundle(rx.recv(65536)) if m.address == "/VMC/Ext/Bone/Pos"}
    sink.close()
    assert set(bones) == {"Head", "LeftEye", "RightEye"}
    for bone in bones:  # rest offsets, not the parent's origin
        np.testing.assert_allclose(bones[bone][:3], STANDARD_REST[bone], atol=1e-7)
    assert bones["LeftEye"][0] < 0 < bones["RightEye"][0]  # Unity +x is the avatar's right
    # Unity: +yaw about +Y looks to the avatar's right; both eyes look to the avatar's left here
    left = Rotation.from_quat(bones["LeftEye"][3:]).as_rotvec()
    right = Rotation.from_quat(bones["RightEye"][3:]).as_rotvec()
    assert left[1] < -0.4 and right[1] < -0.4 and abs(left[0]) < 1e-6
    no_eyes = VmcSink("127.0.0.1", 9, names="perfect-sync")
    dgram = no_eyes.datagrams(SolveResult(0, 0.0, ["jawOpen"], np.array([0.5]), np.array([0, 0, 0, 1.0]),
                                          np.zeros(3)))
    assert {m.params[0] for d in dgram for m in OscBundle(d) if m.address == "/VMC/Ext/Bone/Pos"} == {"Head"}


def test_vmc_avatar_rest_offsets_replace_the_standard_ones():
    rest = {"Head": (0.0, 0.11, -0.01), "LeftEye": (-0.03, 0.05, 0.07)}
    sink = VmcSink("127.0.0.1", 9, names="perfect-sync", rest_offsets=rest)
    dgrams = sink.datagrams(SolveResult(0, 0.0, ["eyeLookOutLeft", "jawOpen"], np.array([0.5, 0.1]),
                                        np.array([0, 0, 0, 1.0]), np.array([4.0, 5.0, 6.0])))
    sink.close()
    msgs = [m for d in dgrams for m in OscBundle(d)]
    check_vmc_spec([(m.address, tuple(m.params)) for m in msgs])
    bones = {m.params[0]: m.params[1:4] for m in msgs if m.address == "/VMC/Ext/Bone/Pos"}
    np.testing.assert_allclose(bones["Head"], rest["Head"], atol=1e-7)
    np.testing.assert_allclose(bones["LeftEye"], rest["LeftEye"], atol=1e-7)
    np.testing.assert_allclose(bones["RightEye"], STANDARD_REST["RightEye"], atol=1e-7)
    with pytest.raises(ValueError, match="rest_offsets"):
        VmcSink("127.0.0.1", 9, rest_offsets={"Neck": (0, 0.1, 0)})


class LiveLinkReceiver:
    """UDP packets decoded by PyLiveLinkFace, each with the receiver's time of day on arrival."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.5)
        self.port = self.sock.getsockname()[1]
        self.packets: list[tuple[PyLiveLinkFace, float]] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                pkt = self.sock.recv(4096)
            except TimeoutError:
                continue
            ok, face = PyLiveLinkFace.decode(pkt)
            assert ok
            self.packets.append((face, now_of_day()))

    def close(self) -> None:
        time.sleep(0.3)
        self._stop.set()
        self.thread.join()
        self.sock.close()


def _seconds(face: PyLiveLinkFace) -> float:
    rate = face.fps / face._denominator
    return (face._frames + face._sub_frame) / rate


def test_livelink_timecode_follows_the_clock_device_stays_subject_is_actor():
    rx = LiveLinkReceiver()
    try:
        run_livecap("--livelink", f"127.0.0.1:{rx.port}", "--actor", "anna", "--max-frames", 480)
    finally:
        rx.close()
    faces = [f for f, _ in rx.packets]
    assert len(faces) > 400
    assert {f.name for f in faces} == {"anna"} and {(f.fps, f._denominator) for f in faces} == {(120, 1)}
    assert len({f.uuid for f in faces}) == 1 and faces[0].uuid == device_id("anna")
    # the timecode is the clock's time of day at capture: the least-delayed packet arrives within a few
    # frames of it (one on a quiet machine; 8.6 ms was seen at load 5 on the 2-core VM), the others later by the
    # session's latency (solve + sinks; on a loaded 2-core VM that grows while the replay solves every frame)
    lag = np.array([arrived - _seconds(f) for f, arrived in rx.packets])
    assert np.abs(lag).min() < 4 / 120, f"no packet within a frame of the clock: lags {np.percentile(lag, [0, 50])}"
    assert np.all(np.diff([_seconds(f) for f in faces]) > 0)  # never repeats or runs backwards
    # the session calibrates on the stream's first 120 frames and publishes them in a burst: their
    # timecodes still keep the capture spacing, a whole number of 120 Hz frames (stale frames may be
    # skipped), never squeezed to the publication rate (issue 37.2: 355-473 steps of half a frame). A frame that
    # arrives earlier than every one before it moves the offset down (slewed), which may shift one step.
    steps = np.diff([_seconds(f) for f in faces]) * 120
    off = np.abs(steps - np.round(steps)) > 0.02
    assert off.mean() < 0.01, f"{off.sum()} of {len(steps)} timecode steps off the frame grid: {steps[off][:8]}"

    rx2 = LiveLinkReceiver()
    try:
        run_livecap("--livelink", f"127.0.0.1:{rx2.port}", "--actor", "anna", "--timecode", "01:02:03:04",
                    "--max-frames", 150, "--fast")
    finally:
        rx2.close()
    first = rx2.packets[0][0]
    assert first._frames == (3600 + 2 * 60 + 3) * 120 + 4 and first._sub_frame == 0
    assert first.uuid == faces[0].uuid  # the same device to Unreal, session after session


def test_livelink_ntsc_rates_and_device_id_bytes():
    assert frame_rate_fraction(59.94) == (60000, 1001) and frame_rate_fraction(29.97) == (30000, 1001)
    assert frame_rate_fraction(120) == (120, 1) and frame_rate_fraction(23.976) == (24000, 1001)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2)
    sink = LiveLinkSink("127.0.0.1", rx.getsockname()[1], subject="bo", fps=59.94, timecode="00:00:10:00")
    sink.publish(SolveResult(0, 0.0, ["jawOpen"], np.array([0.5]), np.array([0, 0, 0, 1.0]), np.zeros(3)))
    pkt = rx.recv(4096)
    sink.close()
    ok, face = PyLiveLinkFace.decode(pkt)
    assert ok and (face.fps, face._denominator) == (60000, 1001)
    assert face._frames == int(10 * 60000 / 1001)  # 10 s at 59.94 fps
    # read as Unreal reads it: uint8 version, then a big-endian int32 length 36 and the bare UUID
    assert pkt[0] == 6 and int.from_bytes(pkt[1:5], "big") == 36 and str(uuid.UUID(pkt[5:41].decode()))
    with pytest.raises(ValueError, match=r"'\$'"):
        encode_livelink(np.zeros(61), 0, device="#" + str(uuid.uuid4()))


def _signature(cell: str) -> str:
    """A CSV cell's form: digits as 9 (so 0.1234567890 and 0.0000000000 are one form)."""
    return re.sub(r"\d", "9", cell)


def test_livelinkface_csv_is_what_the_app_writes(tmp_path):
    app = APP_CSVS / "MySlate_3_Jason_Millers_iPhone.csv"
    if not app.exists():
        pytest.skip(f"real Live Link Face CSVs not found at {APP_CSVS}")
    ours = tmp_path / "take.csv"
    run_livecap("--record-csv", ours, "--csv-layout", "livelinkface", "--max-frames", 300)
    theirs_raw, ours_raw = app.read_bytes(), ours.read_bytes()
    assert b"\r" not in theirs_raw and b"\r" not in ours_raw  # LF line ends, as the app
    theirs_lines, our_lines = theirs_raw.decode().splitlines(), ours_raw.decode().splitlines()
    assert our_lines[0] == theirs_lines[0]  # header, column order, BlendShapeCount
    forms = [set() for _ in theirs_lines[0].split(",")]
    for line in theirs_lines[1:]:
        for i, cell in enumerate(line.split(",")):
            forms[i].add(_signature(cell.lstrip("-")))
    assert len(our_lines) > 60  # 120 Hz results, one row per 60 fps timecode frame as the app (issue 37.3)
    assert len({line[:11] for line in our_lines[1:]}) == len(our_lines) - 1
    frames = set()
    for line in our_lines[1:]:
        cells = line.split(",")
        assert len(cells) == len(forms)
        for i, cell in enumerate(cells):
            assert _signature(cell.lstrip("-")) in forms[i], (i, cell)
        frames.add(int(cells[0].split(":")[3].split(".")[0]))
    assert max(frames) <= 59 and len(frames) > 30  # the frame field counts 00-59 at 60 fps


def test_zmq_weights_carry_solve_quality():
    """valid / markers counts and at_bound travel with each frame (docs/protocol.md §3), read with
    pyzmq + msgpack as a subscriber would, from a real session."""
    import msgpack
    import zmq

    cmd = [sys.executable, "-m", "livecap", "run", "--replay", str(TAKE), "--rig", str(RIG), "--zmq-out",
           "tcp://127.0.0.1:*", "--max-frames", 360]
    proc = subprocess.Popen(list(map(str, cmd)), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    try:
        ready = proc.stdout.readline()
        sub.connect(re.search(r"zmq-out ([^;\s]+)", ready).group(1))
        sub.setsockopt(zmq.SUBSCRIBE, b"weights.")
        sub.setsockopt(zmq.RCVTIMEO, 10000)
        frames = []
        while len(frames) < 100:
            _, payload = sub.recv_multipart()
            msg = msgpack.unpackb(payload, raw=False)
            if msg["type"] == "weights":
                frames.append(msg)
    finally:
        sub.close(0)
        ctx.term()
        proc.wait(timeout=60)
    for msg in frames:
        w = np.frombuffer(msg["weights"], dtype="<f4")
        at = np.frombuffer(msg["at_bound"], dtype=np.int8)
        assert at.shape == w.shape and set(at.tolist()) <= {-1, 0, 1}
        assert np.all(np.abs(w[at == -1]) < 1e-5) and np.all(w[at == 0] > -1e-6)  # demo limits [0, 1]
        assert 0 < msg["valid"] <= msg["markers"] and msg["residual"] >= 0
    assert any((np.frombuffer(m["at_bound"], dtype=np.int8) == 0).any() for m in frames)


@pytest.mark.parametrize("args, names", [(["--timecode", "25:00:00:00"], "--timecode"),
                                         (["--vmc", "9", "--vmc-vrm", "1", "--vrm-map", "nowhere.json"],
                                          "nowhere.json")])
def test_bad_timecode_and_vrm_table_are_one_line(tmp_path, args, names):
    cmd = [sys.executable, "-m", "livecap", "run", "--replay", str(TAKE), "--rig", str(RIG), *args]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 1 and names in done.stderr and len(done.stderr.strip().splitlines()) == 1


@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1),
       st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1),
       st.sampled_from(["y", "z"]))
@settings(max_examples=50, deadline=None)
def test_head_pose_sent_does_not_depend_on_the_capture_axes(q0, q, up):
    """A Z-up volume (Vicon, Qualisys) or an actor facing any way: the world frame rotates every
    pose alike, and the pose relative to the neutral is unchanged (finding 1)."""
    world = Rotation.from_euler("x", 90, degrees=True) if up == "z" else Rotation.from_euler("y", 137, degrees=True)
    neutral, pose = Rotation.from_quat(q0), Rotation.from_quat(q)
    t0, t = np.array([10.0, 1500.0, -30.0]), np.array([25.0, 1490.0, -20.0])
    a = NeutralWindow(1)
    a.relative(neutral.as_quat(), t0)
    b = NeutralWindow(1)
    b.relative((world * neutral).as_quat(), world.apply(t0))
    qa, sa = a.relative(pose.as_quat(), t)
    qb, sb = b.relative((world * pose).as_quat(), world.apply(t))
    assert (Rotation.from_quat(qa) * Rotation.from_quat(qb).inv()).magnitude() < 1e-6
    np.testing.assert_allclose(sa, sb, atol=1e-9)


@given(st.lists(st.floats(0, 2.0), min_size=2, max_size=200))
@settings(max_examples=100, deadline=None)
def test_clock_timecode_never_runs_backwards_and_settles_on_the_clock(delays):
    """Frames at 120 Hz published after random delays (bursts, stalls), then 6 s of prompt ones:
    the clock timecode keeps increasing, its offset to the stream only comes down, and it ends
    within one frame of the clock."""
    import livecap.core.timecode as tcm

    clock = tcm.TimecodeClock("clock", 120.0)
    start, out, sent = 36000.0, [], []
    publish = start
    original = tcm.now_of_day
    try:
        for i, delay in enumerate([*delays, *[0.0] * 720]):  # comes down 1 s per 2 s of frames
            ts = i / 120
            publish = max(publish, start + ts + delay)  # frames leave in order
            tcm.now_of_day = lambda t=publish: t
            out.append(clock.seconds_of_day(ts))
            sent.append(publish)
    finally:
        tcm.now_of_day = original
    out, sent = np.array(out), np.array(sent)
    offset = out - np.arange(len(out)) / 120
    assert np.all(np.diff(out) > 0) and np.all(np.diff(offset) <= 1e-9)
    assert abs(out[-1] - sent[-1]) < 1 / 120
