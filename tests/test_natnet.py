"""NatNet through the ``natnet`` package against a protocol-level Motive stand-in of our own in
another process, written from OptiTrack's published NatNet 4.0 packet layout (unicast: message id
and size as uint16, then server info, data descriptions, frames of data with marker sets, legacy
unlabelled markers, rigid bodies, skeletons, labelled markers, force plates, devices and the
frame suffix). It was not tried against a real Motive."""

import socket
import subprocess
import sys
import textwrap

import numpy as np
import pytest

pytest.importorskip("natnet")
from transport.natnet import NatNetSource, NatNetSourceError  # noqa: E402

SERVER = r"""
import socket, struct, sys, time
n_frames = int(sys.argv[1])
NAMES = ["A", "B", "C"]
sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
sock.bind(("127.0.0.1", 0))
print(sock.getsockname()[1], flush=True)

def send(kind, body, to):
    sock.sendto(struct.pack("<HH", kind, len(body)) + body, to)

def frame(f):
    pts = [(0.01 * i + 0.001 * f, 0.02 * i, 0.03) for i in range(3)]  # metres
    if f == 2:
        pts[1] = (0.0, 0.0, 0.0)  # B occluded
    body = struct.pack("<I", f)
    body += struct.pack("<I", 1) + b"Face\0" + struct.pack("<I", 3) + b"".join(struct.pack("<3f", *p) for p in pts)
    body += struct.pack("<I", 0)  # legacy unlabelled markers
    body += struct.pack("<I", 0) + struct.pack("<I", 0)  # rigid bodies, skeletons
    labelled = [(0x10000 | (i + 1), p, 0x01 if (f == 2 and i == 1) else 0) for i, p in enumerate(pts)]
    labelled.append((7, (0.5, 0.5, 0.5), 0x10))  # an unlabelled point
    body += struct.pack("<I", len(labelled)) + b"".join(
        struct.pack("<I3ffHf", i, *p, 0.01, param, 0.0) for i, p, param in labelled)
    body += struct.pack("<I", 0) + struct.pack("<I", 0)  # force plates, devices
    body += struct.pack("<IIdQQQH", 0, 0, f / 120.0, 0, 0, 0, 0)
    return body

client, streaming = None, False
sock.settimeout(0.05)
f = 0
while f < n_frames:
    try:
        data, addr = sock.recvfrom(65536)
        kind = struct.unpack_from("<H", data)[0]
        if kind == 0:  # connect: server info, NatNet 4.0
            send(1, b"Motive".ljust(256, b"\0") + bytes([3, 0, 0, 0]) + bytes([4, 0, 0, 0]), addr)
            client = addr
        elif kind == 4:  # model definitions
            body = struct.pack("<I", 1) + struct.pack("<I", 0) + b"Face\0" + struct.pack("<I", 3)
            body += b"".join(n.encode() + b"\0" for n in NAMES)
            send(5, body, addr)
            streaming = True
    except socket.timeout:
        pass
    if client is not None and (streaming or sys.argv[2] == "1"):
        time.sleep(0.3) if f == 0 else time.sleep(0.005)
        body = frame(f)
        if f == 4:
            body = body[:30]  # cut short: malformed
        send(7, body, client)
        f += 1
time.sleep(0.5)
"""


def _server(tmp_path, n, unlabelled):
    script = tmp_path / "natnet_server.py"
    script.write_text(textwrap.dedent(SERVER))
    proc = subprocess.Popen([sys.executable, str(script), str(n), "1" if unlabelled else "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, int(proc.stdout.readline())


@pytest.mark.parametrize("unlabelled", [False, True])
def test_natnet_source_against_a_protocol_server(tmp_path, unlabelled):
    proc, port = _server(tmp_path, 8, unlabelled)
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
