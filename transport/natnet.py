"""OptiTrack NatNet (Motive's streaming protocol), unicast.

livecap speaks to the server from its own UDP socket and thread: connect (message 0, the server
answers with its info and NatNet version), ask for the data descriptions (4 -> 5) when the session
needs marker names, keep the stream alive (10, once a second), and read frames of data (7) with
``transport.natnet_frame``, which bounds every count by the packet's length. The descriptions are
read by the ``natnet`` package over a buffer that refuses the same overreach. One malformed
packet, a message id it does not know or a datagram from another host is counted and skipped.

Labelled markers: one marker set (``marker_set``, or the first holding the session's labels)
named by the data descriptions. Unlabelled: every marker of the frame's labelled-marker list
that is not occluded (Motive puts unlabelled points there, model id 0), or the legacy "other
markers" list when that one is empty. Motive streams metres by default.
"""

from __future__ import annotations

import math
import select
import socket
import struct
import threading
import time

import numpy as np

from livecap.core.take import MarkerFrame
from livecap.core.units import MM_PER_UNIT
from transport.capture_queue import QueuedCaptureSource, endpoint
from transport.natnet_frame import NatNetPacketError, Version, parse_frame

DEFAULT_PORT = 1510  # Motive's command port
CONNECT, SERVER_INFO, RESPONSE, REQUEST_MODELDEF, MODELDEF, FRAME, MESSAGE, KEEPALIVE = 0, 1, 3, 4, 5, 7, 8, 10
UNRECOGNISED = 100
QUIET = {RESPONSE, MESSAGE, UNRECOGNISED, KEEPALIVE}  # answers we do not use: neither read nor counted
RECEIVE_BUFFER = 4 << 20  # 2400-point clouds at 120 Hz are 7.5 MB/s: room for half a second


class NatNetSourceError(OSError):
    """No NatNet server answered, or it has no marker set for the session's labels."""


def local_address_for(server: str, port: int) -> str:
    """The address of this machine's interface that routes to ``server`` (no packet is sent): the
    socket binds there, so a Motive on another host is reached and a loopback one stays on loopback."""
    family = socket.AF_INET6 if ":" in server else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM) as probe:
        probe.connect((server, port))
        return probe.getsockname()[0]


def _bounded_buffer(data: bytes):
    """The ``natnet`` package's reader, refusing float arrays and strings beyond the packet's end
    (its own builds ``"f" * count`` first and reads empty strings past the end forever)."""
    from natnet.packet_buffer import PacketBuffer

    class Bounded(PacketBuffer):
        def read_float32_array(self, count: int):
            if count * 4 > len(self.data) - self.pointer:
                raise NatNetPacketError(f"{count} floats claimed, {len(self.data) - self.pointer} bytes left")
            return super().read_float32_array(count)

        def read_string(self, max_length=None, static_length=False):
            if self.pointer >= len(self.data):
                raise NatNetPacketError("a name past the packet's end")
            return super().read_string(max_length, static_length)

    return Bounded(data)


class NatNetSource(QueuedCaptureSource):
    def __init__(self, server: str, port: int = DEFAULT_PORT, labels: list[str] | None = None,
                 unlabelled: bool = False, marker_set: str | None = None, units: str = "m",
                 local: str | None = None, timeout: float = 5.0, idle_timeout: float | None = None) -> None:
        if units not in MM_PER_UNIT:
            raise ValueError(f"NatNet units {units!r}: expected one of {sorted(MM_PER_UNIT)}")
        self.scale = MM_PER_UNIT[units]
        self.unlabelled = unlabelled or labels is None
        self.labels = None if self.unlabelled else list(labels)
        self.marker_set = marker_set
        self._start_queue(f"natnet {endpoint(server, port)}", idle_timeout)
        self.version: Version | None = None
        self.server_name = ""
        self._descriptions = None
        self._names: list[str] = []
        try:
            info = socket.getaddrinfo(server, port, type=socket.SOCK_DGRAM)[0]
            self._server = info[4][:2]
            self._socket = socket.socket(info[0], socket.SOCK_DGRAM)
            self._socket.bind((local or local_address_for(self._server[0], port), 0))
        except OSError as exc:
            raise NatNetSourceError(f"NatNet server {endpoint(server, port)}: {exc}") from None
        self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)
        self._socket.setblocking(False)
        self._last_keepalive = 0.0
        self._ready = False  # frames before the handshake ends (descriptions not read yet) are dropped
        try:
            self._handshake(server, port, timeout)
        except BaseException:
            self._socket.close()
            raise
        self._ready = True
        self._thread = threading.Thread(target=self._receive, daemon=True)
        self._thread.start()

    def _send(self, message: int, body: bytes = b"\0") -> None:
        self._socket.sendto(struct.pack("<HH", message, len(body)) + body, self._server)

    def _handshake(self, server: str, port: int, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        asked = 0.0
        while self.version is None:
            if time.monotonic() > deadline:
                raise NatNetSourceError(f"NatNet server {endpoint(server, port)}: no answer (TimeoutError)")
            if time.monotonic() - asked > 1.0:
                self._send(CONNECT, b"Ping\0")
                asked = time.monotonic()
            self._pump(0.1)
        if self.unlabelled:
            return
        self._send(REQUEST_MODELDEF)
        while self._descriptions is None and time.monotonic() < deadline:
            self._pump(0.1)
        if self._descriptions is None:
            raise NatNetSourceError(f"NatNet server {endpoint(server, port)}: no data descriptions")
        for ms in self._descriptions.marker_sets:
            if (self.marker_set is None and set(ms.marker_names) & set(self.labels)) or ms.name == self.marker_set:
                self.marker_set, self._names = ms.name, list(ms.marker_names)
                break
        else:
            raise NatNetSourceError(f"NatNet server {endpoint(server, port)}: no marker set "
                                    f"{self.marker_set or 'holding the session labels'}")
        where = {lab: i for i, lab in enumerate(self._names)}
        self._map = np.array([where.get(lab, -1) for lab in self.labels])

    # ------------------------------------------------------------------ receiving
    def _pump(self, wait: float) -> None:
        """Read every datagram waiting (after up to ``wait`` s for the first); one bad one is a counted skip."""
        if time.monotonic() - self._last_keepalive > 1.0 and self.version is not None:
            self._send(KEEPALIVE)
            self._last_keepalive = time.monotonic()
        if not select.select([self._socket], [], [], wait)[0]:
            return
        for _ in range(10000):  # bounded: a flood cannot starve the keepalive
            try:
                data, sender = self._socket.recvfrom(65536)
            except BlockingIOError:
                return
            self._message(data, sender)

    def _message(self, data: bytes, sender) -> None:
        if sender[0] != self._server[0]:
            self.bad.skip("malformed", f"a datagram from {sender[0]}, not the server {self._server[0]}")
            return
        if len(data) < 4:
            self.bad.skip("short", f"a {len(data)}-byte datagram")
            return
        message = struct.unpack_from("<H", data)[0]
        body = memoryview(data)[4:]
        if message == FRAME:
            if self._ready:
                self._hand_over(body)
        elif message == SERVER_INFO:
            if len(body) < 264:
                self.bad.skip("short", f"server info of {len(body)} bytes")
                return
            self.server_name = bytes(body[:256]).split(b"\0", 1)[0].decode("utf-8", "replace")
            self.version = (body[260], body[261])
        elif message == MODELDEF:
            self._read_descriptions(body)
        elif message not in QUIET:
            self.bad.skip("unknown_message", f"message id {message} ({len(data)} bytes)")

    def _read_descriptions(self, body) -> None:
        from natnet import DataDescriptions
        from natnet import Version as PackageVersion

        if self.version is None:
            return
        try:
            self._descriptions = DataDescriptions.read_from_buffer(_bounded_buffer(bytes(body)),
                                                                   PackageVersion(*self.version))
        except Exception as exc:  # the package's own readers: struct.error, its protocol errors, ours
            self.bad.skip("malformed", f"unreadable NatNet data descriptions ({type(exc).__name__}: {exc})")

    def _receive(self) -> None:
        while self._running:
            try:
                self._pump(0.2)
            except OSError:  # socket closed under us: the session is over
                break
        self._queue.put(None)

    def decode(self, body) -> MarkerFrame | None:
        """One frame of data's body to a frame, or None (counted) when it cannot be one."""
        try:
            frame = parse_frame(body, self.version)
        except NatNetPacketError as exc:
            self.bad.skip("malformed", f"unreadable NatNet frame ({exc})")
            return None
        if not math.isfinite(frame.timestamp):
            self.bad.skip("nonfinite", f"frame {frame.number}: timestamp {frame.timestamp}")
            return None
        order = self._order.check(frame.number)
        if order:
            self.bad.skip(order, f"frame {frame.number} after {self._order.last}")
            return None
        if self.unlabelled:
            lab = frame.labelled
            keep = (lab["param"] & 0x01) == 0 if "param" in lab.dtype.names else np.ones(len(lab), bool)
            p = lab["pos"][keep] if keep.any() else frame.unlabelled
            p = p.astype(np.float64) * self.scale
            valid = np.isfinite(p).all(1)
            return MarkerFrame(frame.number, frame.timestamp, np.where(valid[:, None], p, 0.0), valid)
        ms = frame.marker_sets.get(self.marker_set)
        if ms is None or len(ms) != len(self._names):
            self.bad.skip("malformed", f"frame {frame.number}: marker set {self.marker_set} missing or resized")
            return None
        p = ms.astype(np.float64) * self.scale
        ok_src = np.isfinite(p).all(1) & (np.abs(p).sum(1) > 0)  # Motive sends an occluded marker as 0,0,0
        has = self._map >= 0
        pos = np.zeros((len(self.labels), 3))
        ok = np.zeros(len(self.labels), dtype=bool)
        pos[has] = p[self._map[has]]
        ok[has] = ok_src[self._map[has]]
        return MarkerFrame(frame.number, frame.timestamp, np.where(ok[:, None], pos, 0.0), ok)

    # ------------------------------------------------------------------ consumer
    def close(self) -> None:
        self._running = False
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        self._socket.close()
