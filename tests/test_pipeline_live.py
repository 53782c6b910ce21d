"""A live session across real processes: ``livecap send`` -> ``livecap run`` -> subscribers.

Every receiver here is its own Python process speaking only the published protocols (pyzmq +
msgpack, python-osc, a Live Link Face decoder written from PyLiveLinkFace's layout); none of
them imports livecap.
"""

import json
import os
import re
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from livecap.calibration.profile import calibrate, estimate_neutral
from livecap.cli.common import load_rig
from transport.recorders import read_csv_recording, read_jsonl_recording, read_marker_recording
from transport.takefile import read_take

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
N_SEND = 240  # frames streamed per session: 2 s at 120 Hz

ZMQ_SUBSCRIBER = """
import json, sys, time, msgpack, numpy as np, zmq
addr, actor, out, idle = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
sock = zmq.Context().socket(zmq.SUB)
sock.connect(addr)
sock.setsockopt(zmq.SUBSCRIBE, ("weights." + actor).encode())
time.sleep(0.5)
print("ready", flush=True)
names, frames, weights, headers, last = {}, [], [], 0, None
deadline = time.monotonic() + 60
while time.monotonic() < deadline:
    if not sock.poll(int(idle * 1000)):
        if last is not None:
            break
        continue
    topic, payload = sock.recv_multipart()
    msg = msgpack.unpackb(payload)
    last = time.monotonic()
    if msg["type"] == "header":
        headers += 1
        names[msg["names_id"]] = msg["names"]
    else:
        frames.append(msg["frame"])
        weights.append(np.frombuffer(msg["weights"], "<f4").tolist())
        assert msg["names_id"] in names, "weights before their header"
json.dump({"names": list(names.values()), "frames": frames, "weights": weights, "headers": headers},
          open(out, "w"))
"""

VMC_SERVER = """
import json, sys, time
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_server import BlockingOSCUDPServer
out, idle = sys.argv[1], float(sys.argv[2])
frames, current, heads, last = [], {}, [], [None]
def val(addr, name, value):
    current[name] = value
    last[0] = time.monotonic()
def apply(addr, *args):
    frames.append(dict(current))
    current.clear()
def bone(addr, name, *pose):
    heads.append([name, *pose])
d = Dispatcher()
d.map("/VMC/Ext/Blend/Val", val)
d.map("/VMC/Ext/Blend/Apply", apply)
d.map("/VMC/Ext/Bone/Pos", bone)
server = BlockingOSCUDPServer(("127.0.0.1", 0), d)
server.timeout = 0.2
print(server.server_address[1], flush=True)
deadline = time.monotonic() + 60
while time.monotonic() < deadline:
    server.handle_request()
    if last[0] is not None and time.monotonic() - last[0] > idle:
        break
json.dump({"frames": frames, "heads": heads}, open(out, "w"))
"""

LIVELINK_RECEIVER = """
import json, socket, struct, sys, time
out, idle = sys.argv[1], float(sys.argv[2])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", 0))
s.settimeout(idle)
print(s.getsockname()[1], flush=True)
packets = []
deadline = time.monotonic() + 60
while time.monotonic() < deadline:
    try:
        pkt = s.recv(4096)
    except socket.timeout:
        if packets:
            break
        continue
    # PyLiveLinkFace's layout: <I version, 37-byte device id, !i name length, name, !if2ib, !61f
    version = struct.unpack("<I", pkt[0:4])[0]
    device = pkt[4:41].decode()
    n = struct.unpack("!i", pkt[41:45])[0]
    name = pkt[45:45 + n].decode()
    frame, sub, fps, den, count = struct.unpack("!if2ib", pkt[45 + n:62 + n])
    values = struct.unpack("!61f", pkt[62 + n:])
    packets.append({"version": version, "device": device, "name": name, "frame": frame, "sub": sub, "fps": fps,
                    "count": count, "values": values})
json.dump(packets, open(out, "w"))
"""


def script(tmp_path, name, text):
    p = tmp_path / f"{name}.py"
    p.write_text(textwrap.dedent(text))
    return p


def spawn(*args, **kw):
    return subprocess.Popen([sys.executable, *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=ENV, **kw)


def livecap(*args):
    return spawn("-m", "livecap", *args)


def first_line(proc, timeout=30.0):
    """The process's first stdout line (it announces readiness or its port)."""
    import selectors

    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    if not sel.select(timeout):
        proc.kill()
        raise AssertionError(f"no output from {proc.args}: {proc.stderr.read()}")
    line = proc.stdout.readline().strip()
    if not line:
        raise AssertionError(f"{proc.args} exited: {proc.stderr.read()}")
    return line


def finish(proc, timeout=60):
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, f"{proc.args} failed ({proc.returncode}):\n{err}"
    return out, err


def free_port(kind=socket.SOCK_STREAM):
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def take_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("live")
    r = subprocess.run([sys.executable, "-m", "livecap", "generate", "--seconds", "3", "--out", str(out)],
                       capture_output=True, text=True, env=ENV, timeout=300)
    assert r.returncode == 0, r.stderr
    import argparse

    rig, layout = load_rig(argparse.Namespace(rig=str(out / "demo_rig.npz"), markers=None))
    take = read_take(out / "demo_take.c3d").select(layout.labels)
    profile = calibrate(rig, layout, estimate_neutral(take, layout.stable, 120))
    profile.save(out / "profile.npz")
    return out


def test_zmq_session_reaches_every_sink(take_dir, tmp_path):
    d = take_dir
    vmc = spawn(script(tmp_path, "vmc", VMC_SERVER), tmp_path / "vmc.json", 2.0)
    llf = spawn(script(tmp_path, "llf", LIVELINK_RECEIVER), tmp_path / "llf.json", 2.0)
    vmc_port, llf_port = int(first_line(vmc)), int(first_line(llf))
    port = free_port()
    run = livecap("run", "--zmq-in", f"tcp://127.0.0.1:{port}", "--zmq-out", "tcp://127.0.0.1:*",
                  "--profile", d / "profile.npz", "--vmc", f"127.0.0.1:{vmc_port}",
                  "--livelink", f"127.0.0.1:{llf_port}", "--record-csv", tmp_path / "w.csv",
                  "--record-jsonl", tmp_path / "w.jsonl", "--record-markers", tmp_path / "m.npz",
                  "--idle-timeout", "1.5", "--no-skip-stale")  # every frame must reach every sink
    ready = first_line(run)
    out_addr = re.search(r"zmq-out ([^;\s]+)", ready).group(1)
    sub = spawn(script(tmp_path, "sub", ZMQ_SUBSCRIBER), out_addr, "actor", tmp_path / "sub.json", 3.0)
    assert first_line(sub) == "ready"
    send = livecap("send", d / "demo_take.c3d", "--zmq", f"tcp://127.0.0.1:{port}", "--end", N_SEND)
    out, _ = finish(send)
    assert f"sent {N_SEND} frames" in out
    report, _ = finish(run)
    for p in (sub, vmc, llf):
        finish(p)
    names = json.loads((tmp_path / "sub.json").read_text())
    profile_names = list(np.load(d / "profile.npz")["names"])

    # ZeroMQ: one weights message per frame, in order, after a header with the right names
    assert names["frames"] == list(range(N_SEND)) and names["headers"] >= 1, report
    assert names["names"] == [profile_names]
    W = np.array(names["weights"])
    assert W.shape == (N_SEND, len(profile_names)) and np.ptp(W, axis=0).max() > 0.2
    assert f"frames in {N_SEND}, out {N_SEND}" in report and "bad input: none" in report

    # VMC: every frame's values then Apply, and the head bone
    vmc_out = json.loads((tmp_path / "vmc.json").read_text())
    heads = [h for h in vmc_out["heads"] if h[0] == "Head"]
    assert len(vmc_out["frames"]) == N_SEND and len(heads) == N_SEND
    assert all(list(f) == profile_names for f in vmc_out["frames"])
    np.testing.assert_allclose([[f[n] for n in profile_names] for f in vmc_out["frames"]], W, atol=1e-6)
    assert {h[0] for h in vmc_out["heads"]} <= {"Head", "LeftEye", "RightEye"}

    # Live Link Face: decodable packets, one per frame, ARKit order
    llf_out = json.loads((tmp_path / "llf.json").read_text())
    assert np.all(np.diff([p["frame"] + p["sub"] for p in llf_out]) > 0)  # time-of-day frame times, increasing
    assert {(p["version"], p["count"], p["fps"], len(p["device"])) for p in llf_out} == {(6, 61, 120, 37)}
    from transport.arkit import ARKIT_NAMES

    j = ARKIT_NAMES.index("jawOpen")
    np.testing.assert_allclose([p["values"][j] for p in llf_out], W[:, profile_names.index("jawOpen")], atol=1e-6)

    # recorders read back what was published
    rec_names, rows = read_jsonl_recording(tmp_path / "w.jsonl")
    assert rec_names == profile_names and [r["frame"] for r in rows] == list(range(N_SEND))
    np.testing.assert_allclose([r["weights"] for r in rows], W, atol=1e-6)  # the wire carries float32
    csv = read_csv_recording(tmp_path / "w.csv", rate=120)
    assert csv.layout == "livelinkface"  # the demo rig's names are ARKit names
    col = {n.lower(): i for i, n in enumerate(csv.names)}
    # the app's layout keeps one row per 60 fps timecode frame (the first result in it): at 120 Hz every other
    # published frame, in order
    rows_w = csv.weights[:, [col[n.lower()] for n in profile_names]]
    assert N_SEND // 2 - 2 <= len(rows_w) < N_SEND  # about one row per two frames (the send is paced at 120 Hz)
    at = [-1]
    for r in rows_w:  # each row is a published frame later than the row before's (capture times jitter)
        at.append(next(i for i in range(at[-1] + 1, len(W)) if np.abs(W[i] - r).max() < 1e-6))
    assert at[1] <= 1
    markers = read_marker_recording(tmp_path / "m.npz")
    assert markers.frames.tolist() == list(range(N_SEND))

    # the raw marker recording replays to the same weights, exactly
    replay = livecap("run", "--replay", tmp_path / "m.npz", "--fast", "--profile",
                     d / "profile.npz", "--record-jsonl", tmp_path / "again.jsonl")
    finish(replay)
    _, again = read_jsonl_recording(tmp_path / "again.jsonl")
    assert [r["weights"] for r in again] == [r["weights"] for r in rows]


def test_osc_session_calibrates_on_the_stream(take_dir, tmp_path):
    d = take_dir
    port = free_port(socket.SOCK_DGRAM)
    run = livecap("run", "--osc-in", f"127.0.0.1:{port}", "--rig", d / "demo_rig.npz", "--neutral-seconds", "0.5",
                  "--zmq-out", "0", "--idle-timeout", "1.5", "--no-skip-stale")
    out_addr = re.search(r"zmq-out ([^;\s]+)", first_line(run)).group(1)
    sub = spawn(script(tmp_path, "sub", ZMQ_SUBSCRIBER), out_addr, "actor", tmp_path / "sub.json", 3.0)
    assert first_line(sub) == "ready"
    finish(livecap("send", d / "demo_take.c3d", "--osc", f"127.0.0.1:{port}", "--end", N_SEND))
    report, _ = finish(run)
    finish(sub)
    got = json.loads((tmp_path / "sub.json").read_text())
    assert got["frames"] == list(range(N_SEND)), report
    assert len(got["names"][0]) == 43 and "jawOpen" in got["names"][0]


def test_kill_9_loses_no_flushed_frame(take_dir, tmp_path):
    d = take_dir
    stats = tmp_path / "stats.json"
    run = livecap("run", "--replay", d / "demo_take.c3d", "--loop", "--profile", d / "profile.npz",
                  "--record-csv", tmp_path / "w.csv", "--csv-layout", "livecap", "--record-jsonl", tmp_path / "w.jsonl",
                  "--record-markers", tmp_path / "m.npz", "--flush-every", "0.05", "--stats-file", stats,
                  "--stats-every", "0.05")
    first_line(run)
    deadline = time.monotonic() + 30
    reported = None
    while time.monotonic() < deadline:
        time.sleep(0.05)
        try:
            s = json.loads(stats.read_text())
        except (OSError, ValueError):
            continue
        if s["marker_recorder"]["flushed"] >= 40:
            reported = s
            break
    run.send_signal(signal.SIGKILL)
    run.communicate(timeout=10)
    assert reported is not None, "the session never reported flushed frames"
    sinks = list(reported["sinks"].values())
    csv = read_csv_recording(tmp_path / "w.csv")
    _, rows = read_jsonl_recording(tmp_path / "w.jsonl")
    assert len(csv.frames) >= sinks[0]["flushed"] and len(rows) >= sinks[1]["flushed"]
    assert csv.frames.tolist() == list(range(len(csv.frames)))
    np.testing.assert_array_equal(csv.weights[: len(rows)][: len(csv.frames)],
                                  np.array([r["weights"] for r in rows])[: len(csv.frames)])
    rec = read_marker_recording(tmp_path / "m.npz.partial")
    assert rec.take.n_frames >= reported["marker_recorder"]["flushed"]
    take = read_take(d / "demo_take.c3d")
    k = rec.take.n_frames
    np.testing.assert_array_equal(rec.take.valid, take.valid[:k])


def test_stuck_subscriber_never_blocks_the_solver(take_dir, tmp_path):
    """A subscriber that never reads: sends fail fast and are counted, every frame is still solved
    and reaches the recorder; nothing here asserts on timing."""
    d = take_dir
    port = free_port()
    run = livecap("run", "--replay", d / "demo_take.c3d", "--profile", d / "profile.npz", "--speed", "4",
                  "--zmq-out", f"tcp://127.0.0.1:{port}", "--zmq-hwm", "1", "--zmq-policy", "count",
                  "--record-jsonl", tmp_path / "w.jsonl",
                  "--stats-file", tmp_path / "stats.json")
    stuck = spawn("-c", textwrap.dedent("""
        import sys, time, zmq
        s = zmq.Context().socket(zmq.SUB)
        s.setsockopt(zmq.RCVHWM, 1)
        s.setsockopt(zmq.RCVBUF, 2048)
        s.connect(sys.argv[1])
        s.setsockopt(zmq.SUBSCRIBE, b"")
        print("ready", flush=True)
        time.sleep(60)
    """), f"tcp://127.0.0.1:{port}")
    first_line(stuck)
    finish(run)
    stuck.kill()
    stuck.communicate()
    s = json.loads((tmp_path / "stats.json").read_text())
    zmq_stats = next(v for k, v in s["sinks"].items() if k.startswith("ZmqSink"))
    take = read_take(d / "demo_take.c3d")
    assert s["frames_in"] == s["frames_out"] == take.n_frames
    assert zmq_stats["drops"] > 0 and zmq_stats["sent"] + zmq_stats["drops"] == take.n_frames
    assert len(read_jsonl_recording(tmp_path / "w.jsonl")[1]) == take.n_frames


@pytest.mark.parametrize("args, names", [
    (["--replay", "nope.c3d", "--profile", "x.npz"], "x.npz"),
    (["--replay", "nope.c3d", "--rig", "{rig}"], "nope.c3d"),
    (["--session", "bad.toml"], "bad.toml"),
    (["--zmq-in", "tcp://0.0.0.0:5555", "--rig", "{rig}"], "--interface"),
])
def test_bad_files_and_flags_are_one_clear_line(take_dir, tmp_path, args, names):
    (tmp_path / "bad.toml").write_text("[sinks]\nnot_an_option = 1\n")
    args = [a.replace("{rig}", str(take_dir / "demo_rig.npz")) for a in args]
    r = subprocess.run([sys.executable, "-m", "livecap", "run", *args], capture_output=True, text=True, env=ENV,
                       cwd=tmp_path, timeout=60)
    assert r.returncode == 1 and names in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
