"""QTM RT through the qtm-rt package against a protocol-level QTM server of our own in another
process, written from Qualisys' published RT protocol layout (little-endian port: 8-byte header of
size and type; command, XML and data packets; data = timestamp, frame number, components; the 3D
component = count, drop rate, out-of-sync rate, then x y z per marker, NaN when lost; 3D-no-labels
adds an id per marker). It was not tried against a real QTM."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("qtm_rt")
from transport.qtm import QtmError, QtmSource, labels_from_parameters  # noqa: E402

SERVERS = str(Path(__file__).with_name("capture_servers.py"))


def _server(frames: int, *extra: str) -> tuple[subprocess.Popen, int]:
    """The fake QTM of tests/capture_servers.py."""
    proc = subprocess.Popen([sys.executable, SERVERS, "qtm", str(frames), *extra], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    return proc, int(proc.stdout.readline())


def test_labels_from_parameters():
    xml = "<QTM_Parameters_Ver_1.25><The_3D><Label><Name>L1</Name></Label><Label><Name>L2</Name></Label></The_3D>" \
          "</QTM_Parameters_Ver_1.25>"
    assert labels_from_parameters(xml) == ["L1", "L2"]


@pytest.mark.parametrize("unlabelled", [False, True])
def test_qtm_source_against_a_protocol_server(unlabelled):
    proc, port = _server(8, "--bad", "4")
    try:
        src = QtmSource("127.0.0.1", port, labels=["C", "A", "B", "Z"], unlabelled=unlabelled, idle_timeout=1.0)
        frames = list(src)
        src.close()
    finally:
        proc.kill()
        proc.wait()
    assert [f.frame for f in frames] == [0, 1, 2, 3, 5, 6, 7]
    assert src.bad.as_dict() == {"malformed": 1}
    f1 = frames[1]
    if unlabelled:
        np.testing.assert_allclose(f1.positions, [[1, 0, 31], [11, 20, 31], [21, 40, 31]])
        assert frames[2].valid.tolist() == [True, False, True]
    else:
        assert src.stream_labels == ["A", "B", "C"]
        np.testing.assert_allclose(f1.positions[:2], [[21, 40, 31], [1, 0, 31]])
        assert f1.valid.tolist() == [True, True, True, False]
        assert frames[2].valid.tolist() == [True, True, False, False]  # B lost


def test_no_qtm_is_one_clear_error():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(QtmError, match="cannot connect"):
        QtmSource("127.0.0.1", port, timeout=1.0)


def test_run_qtm_in_names_a_label_mismatch(tmp_path, demo, capsys):
    """``livecap run --qtm-in``: a QTM whose 3D labels are not the profile's is one clear line."""
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.cli import main
    from livecap.demo.performance import PerformanceSettings, perform

    rig, layout = demo
    take = perform(rig, layout, PerformanceSettings(seconds=1.0)).take
    calibrate(rig, layout, estimate_neutral(take, layout.stable, 60)).save(tmp_path / "p.npz")
    proc, port = _server(3)
    try:
        assert main(["run", "--qtm-in", f"127.0.0.1:{port}", "--profile", str(tmp_path / "p.npz")]) == 1
    finally:
        proc.kill()
        proc.wait()
    assert "none of the session's labels among QTM's (A, B, C" in capsys.readouterr().err


# ------------------------------------------------------------------ issue 36 item 4: hostile packets
def _hostile_server(frames: int, *extra: str) -> tuple[subprocess.Popen, int]:
    return _server(frames, "--hostile", *extra)


@pytest.mark.parametrize("unlabelled", [False, True])
def test_hostile_qtm_packets_counted_skipped_reconnected(unlabelled):
    """A fake QTM sends, among 40 honest frames, an unknown packet type, 2^31 components of size 0,
    50 markers claimed in a 3-marker component, an unknown component, and headers whose size is 0, 4
    and 2^31 (after each of those the stream cannot be followed: it reconnects). Every honest frame
    arrives, every hostile packet is counted, and when QTM is finally gone the source says it is lost
    (qtm_rt's receiver raised on the first of those and the session ended, as if finished)."""
    proc, port = _hostile_server(40)
    try:
        src = QtmSource("127.0.0.1", port, labels=["C", "A", "B"], unlabelled=unlabelled, reconnect_for=1.0)
        frames = list(src)
        src.close()
    finally:
        proc.kill()
        proc.wait()
    assert [f.frame for f in frames] == list(range(40))
    assert src.bad.as_dict() == {"malformed": 7}
    assert src.reconnects == 3
    assert src.lost and "no answer for 1 s" in src.lost


def test_qtm_data_problem_bounds_every_count():
    from tests.capture_servers import qtm_hostile
    from transport.qtm import data_problem

    assert data_problem(qtm_hostile(1, False, "2^31 components of size 0")[8:]).startswith("2147483648 components")
    assert "50 markers" in data_problem(qtm_hostile(1, False, "50 markers claimed")[8:])
    assert "unknown component" in data_problem(qtm_hostile(1, False, "unknown component")[8:])
    assert data_problem(b"\0" * 10) == "data packet of 10 bytes"


def test_run_qtm_in_survives_hostile_packets_and_exits_1_when_qtm_is_gone(tmp_path, demo_profile_path):
    """``livecap run --qtm-in`` against the hostile QTM: the frames after each bad packet are
    published, the bad ones counted, and the session whose source is gone at its end exits 1."""
    import json

    from livecap.calibration.profile import Profile

    profile = Profile.load(demo_profile_path)
    face = tmp_path / "face.json"
    face.write_text(json.dumps({lab: [float(v) for v in p]
                                for lab, p in zip(profile.labels, profile.source_neutral, strict=True)}))
    proc, port = _hostile_server(240, "--face", str(face), "--rate", "120")
    stats = tmp_path / "stats.json"
    try:
        run = subprocess.run([sys.executable, "-m", "livecap", "run", "--qtm-in", f"127.0.0.1:{port}", "--profile",
                              str(demo_profile_path), "--stats-file", str(stats), "--mode", "lsq",
                              "--no-skip-stale", "--idle-timeout", "1"], capture_output=True, text=True, timeout=120)
    finally:
        proc.kill()
        proc.wait()
    st = json.loads(stats.read_text())
    assert run.returncode == 1, run.stderr
    assert "source lost: QTM at 127.0.0.1" in run.stderr
    assert st["frames_in"] == 240 and st["frames_out"] >= 230, st
    assert st["bad_input"].get("malformed") == 7


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200), st.integers(0, 2**31 - 1))
def test_data_problem_never_raises_and_what_it_passes_qtm_rt_can_read(noise, seed):
    """Any bytes as a data packet's body: a reason, or a packet whose 3D components qtm_rt and our
    numpy read agree on (both within the packet)."""
    from qtm_rt.packet import QRTPacket

    from tests.capture_servers import qtm_3d, qtm_data
    from transport.qtm import data_problem

    rng = np.random.default_rng(seed)
    body = bytearray(qtm_data(int(rng.integers(0, 9)), qtm_3d(3, bool(seed % 2)), 2 if seed % 2 else 1)[8:])
    for _ in range(int(rng.integers(0, 6))):
        body[int(rng.integers(0, len(body)))] = int(rng.integers(0, 256))
    for data in (bytes(body), noise):
        if data_problem(data) is None:
            packet = QRTPacket(data)
            got = packet.get_3d_markers() or packet.get_3d_markers_no_label()
            assert got is None or len(got[1]) == got[0].marker_count
