"""The live paths under attack (issue 36): layout eviction (bursts of fresh-layout packets beside an
honest ``livecap send`` must not make the honest stream's id-only packets unknown), lost OSC
datagrams counted, JSONL rows, LSL and the loopback rule. Real processes on loopback, and the
layout table's logic alone."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from transport.wire import LAYOUT_TABLE_SIZE, LayoutTable, UnknownLabel, decode_markers, encode_markers, layout_id

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
SESSION = [f"m{i}" for i in range(6)]


def spawn(*args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=ENV)


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def packet(frame: int, labels: list[str] | None, lid: str) -> bytes:
    n = len(labels) if labels else len(SESSION)
    return encode_markers(frame, frame / 120, np.zeros((n, 3)), np.ones(n, bool), labels, lid)


def test_session_layout_survives_any_burst_and_foreign_layouts_are_refused_unlearned():
    table = LayoutTable(allowed=SESSION)
    lid = table.pin(SESSION)
    for k in range(5 * LAYOUT_TABLE_SIZE):
        labels = [f"x{k}_{j}" for j in range(6)]
        with pytest.raises(UnknownLabel):
            decode_markers(packet(0, labels, layout_id(labels)), table)
    assert list(table) == [lid]
    with pytest.raises(UnknownLabel):  # a refused layout's id-only packets: a wrong --profile, not a lost announcement
        decode_markers(packet(1, None, layout_id(labels)), table)
    for k in range(5 * LAYOUT_TABLE_SIZE):  # the session's own labels in other orders are learned, bounded
        labels = SESSION[k % 6:] + SESSION[:k % 6] if k < 6 else list(np.random.default_rng(k).permutation(SESSION))
        decode_markers(packet(0, labels, layout_id(labels)), table)
    assert len(table) == LAYOUT_TABLE_SIZE and lid in table
    assert decode_markers(packet(1, None, lid), table).labels == SESSION


@pytest.fixture(scope="module")
def d(tmp_path_factory) -> Path:
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from transport.takefile import read_take

    out = tmp_path_factory.mktemp("evict")
    r = subprocess.run([sys.executable, "-m", "livecap", "generate", "--seconds", "3", "--seed", "0", "--out",
                        str(out)], capture_output=True, text=True, env=ENV, timeout=300)
    assert r.returncode == 0, r.stderr
    rig = Rig.load(out / "demo_rig.npz")
    layout = MarkerLayout.load(out / "demo_rig.markers.json", rig)
    take = read_take(out / "demo_take.c3d").select(layout.labels)
    calibrate(rig, layout, estimate_neutral(take, layout.stable, 120)).save(out / "profile.npz")
    return out


def test_layout_burst_beside_an_honest_sender_does_not_starve_it(d, tmp_path):
    """``livecap run`` binds; an honest ``livecap send`` (labels once a second, the layout id in
    between) and the attacker (20 fresh layouts at once, every second) connect. Before the fix
    each burst evicted the honest layout and ~90 % of its frames were counted unknown_layout."""
    addr = f"tcp://127.0.0.1:{free_port()}"
    run = spawn("-m", "livecap", "run", "--zmq-in", addr, "--zmq-in-bind", "--profile", d / "profile.npz",
                "--idle-timeout", 2, "--no-skip-stale", "--stats-file", tmp_path / "s.json")
    assert run.stdout.readline().startswith("ready")
    attacker = spawn("-m", "benchmarks.layout_burst", addr, "--seconds", 6)
    assert attacker.stdout.readline().strip() == "ready"
    send = spawn("-m", "livecap", "send", d / "demo_take.c3d", "--zmq", addr, "--connect", "--loop", "--frames", 480)
    out, err = send.communicate(timeout=120)
    assert send.returncode == 0, err
    burst = json.loads(attacker.communicate(timeout=60)[0].strip().splitlines()[-1])
    _, err = run.communicate(timeout=60)
    assert run.returncode == 0, err
    st = json.loads((tmp_path / "s.json").read_text())
    assert burst["packets"] >= 60
    assert st["bad_input"].get("unknown_layout", 0) == 0, st
    assert st["bad_input"].get("unknown_label", 0) >= burst["packets"] - 40, st  # a burst may precede the connection
    assert st["frames_in"] >= 0.99 * 480, st


def test_osc_frames_that_never_arrive_are_counted_and_the_buffer_reported(d, tmp_path):
    """UDP drops datagrams silently (issue 36.9): the frame numbers the session never saw are
    counted as ``missing``; a sender restart is not a gap. The ready line says what receive
    buffer the kernel gave."""
    from transport.osc_source import encode_osc_frame
    from transport.takefile import read_take

    take = read_take(d / "demo_take.c3d")
    port = free_port(socket.SOCK_DGRAM)
    run = spawn("-m", "livecap", "run", "--osc-in", f"127.0.0.1:{port}", "--profile", d / "profile.npz",
                "--idle-timeout", 1, "--no-skip-stale", "--stats-file", tmp_path / "s.json")
    ready = run.stdout.readline()
    assert "receive buffer" in ready and "KiB" in ready, ready
    lost = {10, 11, 12, 50}
    frames = [f for f in range(120) if f not in lost] + list(range(5))  # then the sender restarts
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for f in frames:
            j = f % take.n_frames
            tx.sendto(encode_osc_frame(f, f / 120, take.labels, take.positions[j], take.valid[j]),
                      ("127.0.0.1", port))
            time.sleep(1 / 240)
    _, err = run.communicate(timeout=60)
    assert run.returncode == 0, err
    st = json.loads((tmp_path / "s.json").read_text())
    assert st["frames_in"] == len(frames), st
    assert st["bad_input"] == {"missing": 4, "stream_restart": 1}, st


def test_jsonl_rows_carry_the_keys_of_the_zeromq_weights_message(tmp_path):
    """docs/protocol.md §6 (issue 36.13): a JSONL row has the ZeroMQ weights message's keys."""
    import msgpack

    from livecap.core.result import SolveResult
    from transport.recorders import JsonlRecorder, read_jsonl_recording
    from transport.wire import decode_payload, encode_weights

    names = ["jawOpen", "eyeBlinkLeft", "mouthSmileLeft"]
    res = SolveResult(7, 0.25, names, np.array([0.5, 1.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]),
                      np.array([1.0, 2.0, 3.0]), 0.4, 0.001, valid=np.array([True, False, True, True]),
                      at_bound=np.array([0, 1, -1], dtype=np.int8))
    rec = JsonlRecorder(tmp_path / "w.jsonl")
    rec.publish(res)
    rec.close()
    got_names, rows = read_jsonl_recording(tmp_path / "w.jsonl")
    header = json.loads((tmp_path / "w.jsonl").read_text().splitlines()[0])
    row = rows[0]
    wire = msgpack.unpackb(encode_weights(res, layout_id(names)))
    assert set(row) == set(wire), set(wire) ^ set(row)
    pkt = decode_payload(encode_weights(res, layout_id(names)))
    assert got_names == names and row["v"] == 1 and row["names_id"] == header["names_id"] == pkt.names_id
    assert (row["valid"], row["markers"]) == (pkt.valid, pkt.markers) == (3, 4)
    assert row["at_bound"] == pkt.at_bound.tolist() == [0, 1, -1]
    assert row["weights"] == pkt.weights.tolist()


def _udp_binds(pid: int) -> set[tuple[str, int]]:
    """(address, port) of every UDP socket process ``pid`` holds, from /proc (IPv4 and IPv6)."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            link = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])
    out = set()
    for table, family in (("udp", socket.AF_INET), ("udp6", socket.AF_INET6)):
        for line in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
            cols = line.split()
            if cols[9] in inodes:
                host, port = cols[1].split(":")
                raw = bytes.fromhex(host)
                raw = raw[::-1] if family == socket.AF_INET else b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4))
                out.add((socket.inet_ntop(family, raw), int(port, 16)))
    return out


@pytest.mark.skipif(not Path("/proc/self/net/udp").exists(), reason="needs Linux /proc")
def test_lsl_out_answers_discovery_on_loopback_only(d, tmp_path):
    """Item 8 of issue 36: without --interface, ``livecap run --lsl-out`` answers LSL discovery on
    127.0.0.1 only (before: on every interface, IPv4 and IPv6), and a local inlet still finds it."""
    pytest.importorskip("pylsl")
    import uuid

    name = f"livecap-test-{uuid.uuid4().hex[:8]}"
    run = spawn("-m", "livecap", "run", "--replay", d / "demo_take.c3d", "--loop", "--profile", d / "profile.npz",
                "--lsl-out", name)
    try:
        assert "lsl-out" in run.stdout.readline()
        time.sleep(0.5)
        binds = _udp_binds(run.pid)
        discovery = {b for b in binds if b[1] == 16571}
        assert discovery == {("127.0.0.1", 16571)}, binds
        probe = spawn("-c", f"import pylsl; print(len(pylsl.resolve_byprop('name', {name!r}, 1, 10)))")
        assert probe.communicate(timeout=60)[0].strip() == "1"
    finally:
        run.terminate()
        run.communicate(timeout=60)


def test_garbage_that_is_not_a_msgpack_map_is_refused_before_unpacking(monkeypatch):
    """Issue 36.10: the frame thread decodes every queued ZeroMQ message; one byte tells most
    garbage from a marker map, so msgpack never runs on it (and it counts as malformed, not short)."""
    import msgpack

    from transport import wire

    calls, unpackb = [], msgpack.unpackb

    def counted(*args, **kw):
        calls.append(1)
        return unpackb(*args, **kw)

    monkeypatch.setattr(wire.msgpack, "unpackb", counted)
    for junk in (b"\x00garbage", b"\xc4\x10abc", msgpack.packb([1, 2, 3]), b"#bundle\x00" + bytes(20)):
        with pytest.raises(wire.MalformedPacket):
            wire.decode_markers(junk)
    assert calls == []
    labels = ["a", "b"]
    assert decode_markers(encode_markers(3, 0.0, np.zeros((2, 3)), np.ones(2, bool), labels), None).frame == 3
    assert calls == [1]


def test_the_honest_streams_layout_survives_a_burst_in_any_label_order():
    """A sender whose label order is not the profile's (a vendor capture): its layout is the one
    the last good frame used, so layouts in the session's labels but other orders cannot evict it."""
    import zmq

    from transport.wire import topic
    from transport.zmq_source import ZmqSource

    ctx = zmq.Context()
    src = ZmqSource("inproc://honest-order", SESSION, bind=True, context=ctx)
    tp = topic("markers", "actor")
    honest = SESSION[::-1]
    lid = layout_id(honest)
    assert src.decode([tp, packet(10, honest, lid)]).frame == 10
    rng = np.random.default_rng(1)
    for _ in range(3 * LAYOUT_TABLE_SIZE):  # shuffled session labels, each a fresh layout (a stale frame number)
        labels = list(rng.permutation(SESSION))
        assert src.decode([tp, packet(10, labels, layout_id(labels))]) is None
    assert src.decode([tp, packet(11, None, lid)]).frame == 11
    assert src.bad.counts["unknown_layout"] == 0
    src.close()
    ctx.term()
