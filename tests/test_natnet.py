"""NatNet through the ``natnet`` package against a protocol-level Motive stand-in of our own in
another process, written from OptiTrack's published NatNet 4.0 packet layout (unicast: message id
and size as uint16, then server info, data descriptions, frames of data with marker sets, legacy
unlabelled markers, rigid bodies, skeletons, labelled markers, force plates, devices and the
frame suffix). It was not tried against a real Motive."""

import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("natnet")
from transport.natnet import NatNetSource, NatNetSourceError  # noqa: E402

SERVERS = str(Path(__file__).with_name("capture_servers.py"))


def _server(n: int) -> tuple[subprocess.Popen, int]:
    """The fake Motive of tests/capture_servers.py: ``n`` frames, frame 4 cut short."""
    proc = subprocess.Popen([sys.executable, SERVERS, "natnet", str(n), "--bad", "4"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, int(proc.stdout.readline())


@pytest.mark.parametrize("unlabelled", [False, True])
def test_natnet_source_against_a_protocol_server(unlabelled):
    proc, port = _server(8)
    try:
        src = NatNetSource("127.0.0.1", port, labels=["C", "A", "B", "Z"], unlabelled=unlabelled, idle_timeout=1.0)
        frames = list(src)
        src.close()
    finally:
        proc.kill()
        proc.wait()
    assert [f.frame for f in frames] == [0, 1, 2, 3, 5, 6, 7]
    assert src.bad.as_dict() == {"malformed": 1}
    f1 = frames[1]
    if unlabelled:  # every visible point of the labelled-marker list, in mm
        np.testing.assert_allclose(f1.positions, [[1, 0, 30], [11, 20, 30], [21, 40, 30], [500, 500, 500]],
                                   rtol=1e-5)
        assert len(frames[2].positions) == 3
    else:
        assert src.marker_set == "Face"
        np.testing.assert_allclose(f1.positions[:2], [[21, 40, 30], [1, 0, 30]], rtol=1e-5)
        assert f1.valid.tolist() == [True, True, True, False]
        assert frames[2].valid.tolist() == [True, True, False, False]  # B lost


def test_no_server_is_one_clear_error():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(NatNetSourceError, match="no answer"):
        NatNetSource("127.0.0.1", port, timeout=0.5)


# ------------------------------------------------------------------ issue 36 item 3: hostile packets
from tests.capture_servers import natnet_frame, natnet_hostile  # noqa: E402


def _peak_bytes(fn) -> int:
    import tracemalloc

    tracemalloc.start()
    try:
        fn()
    except Exception:
        pass
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def test_no_hostile_frame_allocates_more_than_twice_an_honest_one():
    """Every count is bounded by the bytes left before anything is allocated. A hostile frame is an
    honest 60-point frame with one count bombed (up to 2^32-1 in 4 bytes): receiving and parsing it
    (the datagram's copy, the parse, the error) peaks at most at twice what the honest frame needs
    (the natnet package's reader built a 4 GB format string for the first)."""
    from transport.natnet_frame import NatNetPacketError, parse_frame

    honest = natnet_frame(1, 60)
    parse_frame(memoryview(honest), (4, 0))  # warm: imports, numpy dtype caches
    need = _peak_bytes(lambda: parse_frame(memoryview(honest), (4, 0)))
    checked = 0
    for _, body in natnet_hostile(1, 60)[:6]:  # the five bombs and a cut frame
        with pytest.raises(NatNetPacketError):
            parse_frame(body, (4, 0))
        assert _peak_bytes(lambda body=body: parse_frame(memoryview(body), (4, 0))) <= 2 * need, body[:40]
        checked += 1
    assert checked == 6


def test_parse_frame_reads_what_the_natnet_package_reads():
    """Our bounded reader and the package's agree on an honest frame (positions, ids, params, time)."""
    from natnet import DataFrame, Version
    from natnet.packet_buffer import PacketBuffer

    from transport.natnet_frame import parse_frame

    body = natnet_frame(2)
    ours, theirs = parse_frame(body, (4, 0)), DataFrame.read_from_buffer(PacketBuffer(body), Version(4, 0))
    assert ours.number == theirs.prefix.frame_number and ours.timestamp == theirs.suffix.timestamp
    np.testing.assert_array_equal(ours.marker_sets["Face"], theirs.marker_sets[0].marker_pos_list)
    np.testing.assert_array_equal(ours.labelled["pos"], [m.pos for m in theirs.labeled_markers])
    assert ours.labelled["param"].tolist() == [m.param for m in theirs.labeled_markers]
    assert ours.labelled["id"].tolist() == [m.id_num for m in theirs.labeled_markers]


@pytest.mark.parametrize("unlabelled", [False, True])
def test_hostile_natnet_server_every_packet_counted_no_frame_lost(unlabelled):
    """A fake Motive in another process sends, after every fifth honest frame, the bombs above, a
    cut frame, NaN and inf timestamps, an unknown message id and bombed descriptions: every honest
    frame arrives, every hostile packet is counted, and the receiving process stays small."""
    import json
    import tracemalloc

    proc = subprocess.Popen([sys.executable, SERVERS, "natnet", "30", "--hostile"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        port = int(proc.stdout.readline())
        tracemalloc.start()
        src = NatNetSource("127.0.0.1", port, labels=["C", "A", "B"], unlabelled=unlabelled, idle_timeout=1.0)
        frames = list(src)
        src.close()
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        sent = json.loads(proc.communicate(timeout=10)[0].strip().splitlines()[-1])
    finally:
        proc.kill()
        proc.wait()
    rounds = sent["hostile"] // len(natnet_hostile(0))
    assert [f.frame for f in frames] == list(range(30))
    assert src.bad.as_dict() == {"malformed": 7 * rounds, "nonfinite": 2 * rounds, "unknown_message": rounds}
    assert all(np.isfinite(f.timestamp) for f in frames)
    assert peak < 8e6, peak  # a single bomb of the old reader was 4.1 GB


def test_host_port_parses_ipv6_and_the_loopback_rule_holds():
    from transport.capture import capture_source, host_port

    assert host_port("::1", 1510) == ("::1", 1510)
    assert host_port("[::1]:3883", 1510) == ("::1", 3883)
    assert host_port("[fe80::1]", 22223) == ("fe80::1", 22223)
    assert host_port("10.1.2.3:99", 1510) == ("10.1.2.3", 99)
    assert host_port("motive", 1510) == ("motive", 1510)
    from transport.capture_queue import endpoint

    assert endpoint("::1", 3883) == "[::1]:3883" and endpoint("10.1.2.3", 99) == "10.1.2.3:99"
    for bad in ("[::1", "[::1]x", "host:port", "host:0", "host:70000"):
        with pytest.raises(ValueError):
            host_port(bad, 1510)
    with pytest.raises(ValueError, match="--interface 10.1.2.3"):  # refused before any packet is sent
        capture_source(None, "10.1.2.3", ["A"], False, None)
    with pytest.raises(ValueError, match="--interface 10.1.2.3"):
        capture_source("10.1.2.3:22223", None, ["A"], False, None)


def test_natnet_binds_the_interface_that_reaches_the_server():
    """Not 127.0.0.1 for a server elsewhere: the kernel's route to it (no packet is sent)."""
    from transport.natnet import local_address_for

    assert local_address_for("127.0.0.1", 1510) == "127.0.0.1"
    assert local_address_for("::1", 1510) == "::1"
    try:
        away = local_address_for("192.0.2.1", 1510)  # TEST-NET-1: routed by a default route if any
    except OSError:
        pytest.skip("no route off this machine")
    assert away != "127.0.0.1"


def test_natnet_over_ipv6_loopback():
    """An IPv6 server address works end to end (the socket family follows the server)."""
    proc = subprocess.Popen([sys.executable, SERVERS, "natnet", "4", "--host", "::1"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        port = int(proc.stdout.readline())
        src = NatNetSource("::1", port, unlabelled=True, idle_timeout=1.0)
        frames = list(src)
        src.close()
    finally:
        proc.kill()
        proc.wait()
    assert [f.frame for f in frames] == [0, 1, 2, 3]


@settings(max_examples=300, deadline=None)
@given(st.sampled_from([(2, 5), (2, 9), (2, 11), (3, 0), (4, 0), (4, 1)]), st.integers(0, 2**31 - 1),
       st.integers(0, 12))
def test_any_mangled_frame_is_read_or_refused_never_crashes(version, seed, flips):
    """An honest frame with bytes flipped, cut or grown, read as any NatNet version: a frame or a
    NatNetPacketError, nothing else, and never more than the packet's size in points."""
    from transport.natnet_frame import NatNetPacketError, parse_frame

    rng = np.random.default_rng(seed)
    body = bytearray(natnet_frame(int(rng.integers(0, 9)), int(rng.integers(0, 80))))
    for _ in range(flips):
        body[int(rng.integers(0, len(body)))] = int(rng.integers(0, 256))
    if rng.random() < 0.3:
        body = body[: int(rng.integers(0, len(body)))]
    elif rng.random() < 0.2:
        body += rng.bytes(int(rng.integers(1, 64)))
    try:
        frame = parse_frame(bytes(body), version)
    except NatNetPacketError:
        return
    points = sum(len(p) for p in frame.marker_sets.values()) + len(frame.unlabelled) + len(frame.labelled)
    assert points * 12 <= len(body)


def test_run_natnet_in_publishes_every_frame_beside_hostile_packets(tmp_path, demo_profile_path):
    """``livecap run --natnet-in`` against the hostile fake Motive (the demo actor's markers): the
    frames after every bad packet are published, the bad ones counted, exit 0."""
    import json

    from livecap.calibration.profile import Profile

    profile = Profile.load(demo_profile_path)
    face = tmp_path / "face.json"
    face.write_text(json.dumps({lab: [float(v) for v in p]
                                for lab, p in zip(profile.labels, profile.source_neutral, strict=True)}))
    proc = subprocess.Popen([sys.executable, SERVERS, "natnet", "120", "--hostile", "--face", str(face), "--rate",
                             "120"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stats = tmp_path / "stats.json"
    try:
        port = int(proc.stdout.readline())
        run = subprocess.run([sys.executable, "-m", "livecap", "run", "--natnet-in", f"127.0.0.1:{port}", "--profile",
                              str(demo_profile_path), "--stats-file", str(stats), "--mode", "lsq", "--no-skip-stale",
                              "--idle-timeout", "1"], capture_output=True, text=True, timeout=120)
    finally:
        proc.kill()
        proc.wait()
    st = json.loads(stats.read_text())
    assert run.returncode == 0, run.stderr
    assert st["frames_in"] == st["frames_out"] == 120, st
    assert st["bad_input"] == {"malformed": 7 * 24, "nonfinite": 2 * 24, "unknown_message": 24}


def test_frames_from_another_host_are_counted_not_used():
    """Only the server's datagrams are read: a frame sent to our socket from 127.0.0.2 is counted."""
    import json
    import struct

    proc = subprocess.Popen([sys.executable, SERVERS, "natnet", "40"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        port = int(proc.stdout.readline())
        src = NatNetSource("127.0.0.1", port, unlabelled=True, idle_timeout=1.0)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rogue:
            rogue.bind(("127.0.0.2", 0))
            for f in (1000, 1001, 1002):
                body = natnet_frame(f)
                rogue.sendto(struct.pack("<HH", 7, len(body)) + body, src._socket.getsockname())
        frames = list(src)
        src.close()
        json.loads(proc.communicate(timeout=10)[0].strip().splitlines()[-1])
    finally:
        proc.kill()
        proc.wait()
    assert [f.frame for f in frames] == list(range(40))
    assert src.bad.as_dict() == {"malformed": 3}
