"""Fake capture-system servers on loopback, honest frames with hostile packets among them (issue 36
items 3 and 4), for tests/test_natnet.py, tests/test_qtm.py and benchmarks/hostile.py.

    python tests/capture_servers.py natnet FRAMES [--hostile] [--points N] [--rate HZ] [--face FACE.json]
    python tests/capture_servers.py qtm FRAMES [--hostile] [--rate HZ] [--face FACE.json]

Prints the port, serves one client, streams FRAMES honest frames (numbered 0..FRAMES-1), then
prints one JSON line: what was sent. Written from the published layouts (NatNet 4.0 unicast frames
of data as the ``natnet`` package reads them; QTM RT 1.25 little-endian), never tried against
Motive or QTM.
"""

from __future__ import annotations

import argparse
import json
import math
import socket
import struct
import sys
import time

import numpy as np

NAMES = ["A", "B", "C"]
BOMB = 2**32 - 1  # the largest count a uint32 can claim


# ---------------------------------------------------------------------------------------- NatNet
LABELLED = np.dtype([("id", "<u4"), ("pos", "<f4", (3,)), ("size", "<f4"), ("param", "<u2"), ("residual", "<f4")])


def natnet_frame(f: int, points: int = 0, *, face=None, timestamp: float | None = None,
                 force: bytes = b"\0\0\0\0", devices: bytes = b"\0\0\0\0", set_count: int | None = None,
                 labelled_count: int | None = None) -> bytes:
    """A NatNet 4.0 frame-of-data body: marker set "Face" (``face``, metres, breathing 0.1 mm; by
    default A, B, C with B occluded at frame 2), the labelled-marker list (the face's markers and
    one unlabelled point; or, with ``points``, that many unlabelled points: the face's, then ghosts
    uniform in a 2 m cube about it), force plates and devices as given (raw bytes after their
    count's place), the suffix."""
    if face is None:
        pts = np.array([(0.01 * i + 0.001 * f, 0.02 * i, 0.03) for i in range(3)])
        if f == 2:
            pts[1] = 0.0
    else:
        pts = np.asarray(face, dtype=np.float64) + [0.0, 1e-4 * math.sin(f / 20), 0.0]
    body = struct.pack("<I", f)
    body += struct.pack("<I", 1) + b"Face\0" + struct.pack("<I", len(pts) if set_count is None else set_count)
    body += pts.astype("<f4").tobytes()
    body += struct.pack("<III", 0, 0, 0)  # legacy unlabelled, rigid bodies, skeletons
    if points:
        lab = np.zeros(points, LABELLED)
        k = min(points, len(pts))
        lab["pos"][:k] = pts[:k]
        lab["pos"][k:] = pts.mean(0) + np.random.default_rng(f).uniform(-1.0, 1.0, (points - k, 3))
        lab["id"], lab["param"] = np.arange(points), 0x10
    else:
        lab = np.zeros(len(pts) + 1, LABELLED)
        lab["id"][:-1] = 0x10000 | np.arange(1, len(pts) + 1)
        lab["pos"][:-1], lab["pos"][-1] = pts, 0.5
        lab["param"][-1] = 0x10
        if f == 2 and face is None:
            lab["param"][1] = 0x01
    lab["size"] = 0.01
    body += struct.pack("<I", len(lab) if labelled_count is None else labelled_count) + lab.tobytes()
    body += force + devices
    body += struct.pack("<IIdQQQH", 0, 0, f / 120.0 if timestamp is None else timestamp, 0, 0, 0, 0)
    return body


def natnet_hostile(f: int, points: int = 0) -> list[tuple[int, bytes]]:
    """(message id, body) of every hostile NatNet packet: honest frame ``f`` with one thing changed."""
    plate = struct.pack("<III", 1, 9, 1)  # one force plate, id 9, one channel ...
    return [
        (7, natnet_frame(f, points, force=plate + struct.pack("<I", BOMB))),  # ... of 2^32-1 floats (the 4.1 GB bomb)
        (7, natnet_frame(f, points, devices=plate + struct.pack("<I", 2**24))),  # a device channel of 2^24 floats
        (7, natnet_frame(f, points, force=struct.pack("<I", BOMB))),  # 2^32-1 force plates
        (7, natnet_frame(f, points, set_count=BOMB)),  # a marker set of 2^32-1 markers
        (7, natnet_frame(f, points, labelled_count=BOMB)),  # 2^32-1 labelled markers
        (7, natnet_frame(f, points)[:30]),  # cut short
        (7, natnet_frame(f, points, timestamp=math.nan)),  # NaN timestamp
        (7, natnet_frame(f, points, timestamp=math.inf)),
        (77, b"\x01\x02\x03"),  # an unknown message id
        (5, struct.pack("<III", 1, 0, BOMB) + b"Face\0" + struct.pack("<I", BOMB)),  # descriptions: 2^32-1 names
    ]


def serve_natnet(frames: int, hostile: bool, points: int, rate: float, labels: list[str] = NAMES,
                 face=None, bad_frame: int | None = None, host: str = "127.0.0.1") -> dict:
    """``bad_frame``: that frame is sent cut short (malformed) instead of whole."""
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host, 0))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    print(sock.getsockname()[1], flush=True)
    sent = {"frames": 0, "hostile": 0}

    def send(kind: int, body: bytes, to) -> None:
        sock.sendto(struct.pack("<HH", kind, len(body) & 0xFFFF) + body, to)

    client = None
    f = 0
    t0 = None
    while f < frames:
        due = 0.05 if t0 is None else t0 + f / rate - time.monotonic()
        sock.settimeout(min(max(due, 1e-4), 0.05))  # wake for the next frame: paced, not in bursts
        try:
            data, addr = sock.recvfrom(65536)
            kind = struct.unpack_from("<H", data)[0]
            if kind == 0:  # connect: server info, NatNet 4.0
                send(1, b"Motive".ljust(256, b"\0") + bytes([3, 0, 0, 0]) + bytes([4, 0, 0, 0]), addr)
                client = addr
            elif kind == 4:  # model definitions
                body = struct.pack("<I", 1) + struct.pack("<I", 0) + b"Face\0" + struct.pack("<I", len(labels))
                send(5, body + b"".join(n.encode() + b"\0" for n in labels), addr)
        except TimeoutError:
            pass
        if client is None:
            continue
        if t0 is None:
            t0 = time.monotonic() + 0.3  # the client asks for the descriptions and gets ready to read
        while f < frames and time.monotonic() - t0 >= f / rate:
            body = natnet_frame(f, points, face=face)
            send(7, body[:30] if f == bad_frame else body, client)
            sent["frames"] += 1
            if hostile and f % 5 == 1:
                for kind, body in natnet_hostile(f, points):
                    send(kind, body, client)
                    sent["hostile"] += 1
            f += 1
    time.sleep(0.5)
    return sent


# ---------------------------------------------------------------------------------------- QTM
QTM_HOSTILE_FRAMING = ("size 0", "size 4", "size 2^31")  # the stream cannot be followed after these


def qtm_data(frame: int, body3d: bytes, ctype: int = 1, components: bytes | None = None) -> bytes:
    comp = struct.pack("<II", 8 + len(body3d), ctype) + body3d if components is None else components
    count = 1 if components is None else 2**31
    body = struct.pack("<qII", frame * 8333, frame, count) + comp
    return struct.pack("<II", 8 + len(body), 3) + body


def qtm_3d(frame: int, unlabelled: bool, positions=None) -> bytes:
    if positions is None:
        pts = [(10.0 * i + frame, 20.0 * i, 30.0 + frame) for i in range(3)]
    else:  # a face at rest, breathing 0.1 mm
        pts = [(x, y + 0.1 * math.sin(frame / 20), z) for x, y, z in positions]
    if frame == 2:
        pts[1] = (math.nan,) * 3
    if unlabelled:
        return struct.pack("<Ihh", len(pts), 0, 0) + b"".join(struct.pack("<3fi", *p, 100 + i)
                                                              for i, p in enumerate(pts))
    return struct.pack("<Ihh", len(pts), 0, 0) + b"".join(struct.pack("<3f", *p) for p in pts)


def qtm_hostile(frame: int, unlabelled: bool, which: str) -> bytes:
    ctype = 2 if unlabelled else 1
    honest = qtm_3d(frame, unlabelled)
    return {
        "size 0": struct.pack("<II", 0, 3) + b"\0" * 16,
        "size 4": struct.pack("<II", 4, 3) + b"\0" * 16,
        "size 2^31": struct.pack("<II", 2**31, 3) + b"\0" * 16,
        "unknown type": struct.pack("<II", 12, 77) + b"abcd",
        "2^31 components of size 0": qtm_data(frame, b"", components=struct.pack("<II", 0, ctype)),
        "50 markers claimed": qtm_data(frame, struct.pack("<Ihh", 50, 0, 0) + honest[8:], ctype),
        "unknown component": qtm_data(frame, honest, ctype=999),
    }[which]


def serve_qtm(frames: int, hostile: bool, rate: float, labels: list[str] = NAMES, positions=None,
              bad_frame: int | None = None) -> dict:
    """One client at a time; a hostile packet that breaks the framing is followed by closing the
    connection (as a real stream would be unreadable after it); the next connection goes on.
    ``bad_frame``: that frame is sent claiming 50 markers (malformed) instead of whole."""
    import threading

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    print(srv.getsockname()[1], flush=True)
    sent = {"frames": 0, "hostile": 0, "connections": 0}
    kinds = ["unknown type", "2^31 components of size 0", "50 markers claimed", "unknown component",
             *QTM_HOSTILE_FRAMING] if hostile else []
    state = {"f": 0}
    while state["f"] < frames:
        srv.settimeout(10.0)
        try:
            conn, _ = srv.accept()
        except TimeoutError:
            break
        sent["connections"] += 1
        lock = threading.Lock()

        def packet(kind: int, body: bytes, conn=conn, lock=lock) -> None:
            with lock:
                conn.sendall(struct.pack("<II", 8 + len(body), kind) + body)

        def stream(unlabelled: bool, conn=conn, lock=lock) -> None:
            t0 = time.monotonic() - state["f"] / rate
            try:
                while state["f"] < frames:
                    f = state["f"]
                    time.sleep(max(0.0, t0 + f / rate - time.monotonic()))
                    out = (qtm_hostile(f, unlabelled, "50 markers claimed") if f == bad_frame else
                           qtm_data(f, qtm_3d(f, unlabelled, positions), 2 if unlabelled else 1))
                    bad = kinds.pop(0) if kinds and f % 5 == 1 else None
                    with lock:
                        conn.sendall(out)
                        sent["frames"] += 1
                        state["f"] += 1
                        if bad:
                            conn.sendall(qtm_hostile(f, unlabelled, bad))
                            sent["hostile"] += 1
                    if bad in QTM_HOSTILE_FRAMING:
                        conn.shutdown(socket.SHUT_RDWR)
                        return
            except OSError:
                return

        packet(1, b"QTM RT Interface connected\0")
        buf = b""
        conn.settimeout(0.2)
        while True:
            try:
                chunk = conn.recv(4096)
            except TimeoutError:
                if state["f"] >= frames:
                    break
                continue
            except OSError:
                break
            if not chunk:
                break
            buf += chunk
            while len(buf) >= 8:
                size, _ = struct.unpack_from("<II", buf)
                if len(buf) < size:
                    break
                text, buf = buf[8:size].rstrip(b"\0").decode().lower(), buf[size:]
                if text.startswith("version"):
                    packet(1, ("Version set to " + text.split()[1]).encode() + b"\0")
                elif text == "getparameters 3d":
                    names = "".join(f"<Label><Name>{n}</Name></Label>" for n in labels)
                    packet(2, f"<QTM_Parameters_Ver_1.25><The_3D>{names}</The_3D></QTM_Parameters_Ver_1.25>\0"
                           .encode())
                elif text.startswith("streamframes stop"):
                    pass
                elif text.startswith("streamframes"):
                    threading.Thread(target=stream, args=("3dnolabels" in text,), daemon=True).start()
        conn.close()
    srv.close()  # the capture system is gone: a client's reconnects fail from here on
    return sent


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("system", choices=["natnet", "qtm"])
    p.add_argument("frames", type=int)
    p.add_argument("--hostile", action="store_true")
    p.add_argument("--points", type=int, default=0, help="natnet: unlabelled points per frame (0: 3 + 1)")
    p.add_argument("--rate", type=float, default=200.0)
    p.add_argument("--face", help="a JSON file {label: [x, y, z] mm} streamed instead of A, B, C")
    p.add_argument("--bad", type=int, help="this frame malformed instead of whole (natnet: cut; qtm: 50 markers)")
    p.add_argument("--host", default="127.0.0.1", help="natnet: the address to serve on (::1: IPv6)")
    a = p.parse_args()
    face = json.loads(open(a.face).read()) if a.face else None
    if a.system == "natnet" and face:  # Motive streams metres
        sent = serve_natnet(a.frames, a.hostile, a.points, a.rate, list(face), np.array(list(face.values())) / 1000,
                            a.bad, a.host)
    elif a.system == "natnet":
        sent = serve_natnet(a.frames, a.hostile, a.points, a.rate, bad_frame=a.bad, host=a.host)
    elif face:
        sent = serve_qtm(a.frames, a.hostile, a.rate, list(face), list(face.values()), a.bad)
    else:
        sent = serve_qtm(a.frames, a.hostile, a.rate, bad_frame=a.bad)
    print(json.dumps(sent), flush=True)


if __name__ == "__main__":
    sys.exit(main())
