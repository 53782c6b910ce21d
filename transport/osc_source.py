"""OSC server source: one OSC bundle per frame over UDP (OSC 1.0, opensoundcontrol.org).

Address scheme (wire version 1, see docs/protocol.md)::

    #bundle
      /livecap/frame   ,iidi  version frame timestamp(seconds, double) count
      /livecap/marker  ,sfff  label x y z      (mm; one per VISIBLE marker, ``count`` of them)

A marker that is not in the bundle is missing for that frame. Packets that are not a bundle,
carry the wrong version, fewer markers than ``count``, NaN, unknown or repeated labels, or an
old frame number are counted in :attr:`bad` and skipped.
"""

from __future__ import annotations

import logging
import queue
import socket
import threading
import time
from collections.abc import Iterator, Sequence

import numpy as np
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message import OscMessage
from pythonosc.osc_message_builder import OscMessageBuilder

from livecap.core.take import MarkerFrame
from transport.badinput import BadInput, FrameOrder
from transport.wire import WIRE_VERSION

FRAME_ADDRESS = "/livecap/frame"
MARKER_ADDRESS = "/livecap/marker"
MAX_DATAGRAM = 65507  # the largest UDP payload over IPv4; a frame of 60 markers is ~3 KB
DRAIN = 1000  # datagrams decoded per look before the loop checks stop and idle time
# Kernel receive buffer asked for: 4 MiB holds ~1300 bundles of 60 markers (~11 s at 120 Hz) while the
# reader thread is descheduled on a loaded machine; the kernel may give less (net.core.rmem_max).
RCVBUF = 1 << 22

log = logging.getLogger("livecap.input")


def encode_osc_frame(frame: int, timestamp: float, labels: Sequence[str], positions: np.ndarray,
                     valid: np.ndarray) -> bytes:
    """One frame as an OSC bundle (the datagram ``livecap send --osc`` emits)."""
    valid = np.asarray(valid, dtype=bool)
    bundle = OscBundleBuilder(IMMEDIATELY)
    head = OscMessageBuilder(FRAME_ADDRESS)
    head.add_arg(WIRE_VERSION, "i")
    head.add_arg(int(frame), "i")
    head.add_arg(float(timestamp), "d")
    head.add_arg(int(valid.sum()), "i")
    bundle.add_content(head.build())
    for lab, p, ok in zip(labels, np.asarray(positions, dtype=float), valid, strict=True):
        if ok:
            m = OscMessageBuilder(MARKER_ADDRESS)
            m.add_arg(str(lab), "s")
            for c in p:
                m.add_arg(float(c), "f")
            bundle.add_content(m.build())
    return bundle.build().dgram


class OscDecodeError(ValueError):
    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(detail)
        self.kind = kind


def decode_osc_frame(dgram: bytes, where: dict[str, int]) -> tuple[int, float, np.ndarray, np.ndarray]:
    """Frame number, timestamp, positions (n x 3) and valid (n) in the order of ``where``
    (label -> index). Raises :class:`OscDecodeError` with the bad-input kind."""
    _check_datagram(dgram)
    try:
        contents = list(OscBundle(dgram))
    except Exception as exc:  # python-osc raises ParseError, IndexError, struct.error... on garbage
        kind = "short" if "too short" in str(exc).lower() or "not enough" in str(exc).lower() else "malformed"
        raise OscDecodeError(kind, f"unparseable bundle ({type(exc).__name__}: {exc})") from None
    if not contents or not isinstance(contents[0], OscMessage) or contents[0].address != FRAME_ADDRESS:
        raise OscDecodeError("malformed", f"bundle does not start with {FRAME_ADDRESS}")
    head = contents[0].params
    if len(head) < 1 or not isinstance(head[0], int):
        raise OscDecodeError("malformed", f"{FRAME_ADDRESS} has no version")
    if head[0] != WIRE_VERSION:
        raise OscDecodeError("version", f"OSC wire version {head[0]}, this build speaks {WIRE_VERSION}")
    if len(head) != 4 or not isinstance(head[1], int) or not isinstance(head[2], float) \
            or not isinstance(head[3], int) or isinstance(head[3], bool):
        raise OscDecodeError("malformed", f"{FRAME_ADDRESS} arguments must be ,iidi")
    frame, timestamp, count = head[1], head[2], head[3]
    if not np.isfinite(timestamp):
        raise OscDecodeError("nonfinite", "timestamp is not finite")
    n = len(where)
    positions = np.zeros((n, 3))
    valid = np.zeros(n, dtype=bool)
    markers = contents[1:]
    if len(markers) < count:
        raise OscDecodeError("short", f"bundle has {len(markers)} markers, header says {count}")
    if len(markers) > count:
        raise OscDecodeError("malformed", f"bundle has {len(markers)} markers, header says {count}")
    for m in markers:
        if not isinstance(m, OscMessage) or m.address != MARKER_ADDRESS:
            raise OscDecodeError("malformed", "unexpected message in a frame bundle")
        p = m.params
        if len(p) != 4 or not isinstance(p[0], str) or not all(isinstance(c, float) for c in p[1:]):
            raise OscDecodeError("malformed", f"{MARKER_ADDRESS} arguments must be ,sfff")
        i = where.get(p[0])
        if i is None:
            raise OscDecodeError("unknown_label", f"unknown label {p[0]!r}")
        if valid[i]:
            raise OscDecodeError("duplicate_label", f"label {p[0]!r} appears twice")
        xyz = np.array(p[1:], dtype=float)
        if not np.isfinite(xyz).all():
            raise OscDecodeError("nonfinite", f"marker {p[0]!r} is not finite")
        positions[i] = xyz
        valid[i] = True
    return frame, timestamp, positions, valid


def _check_datagram(dgram: bytes) -> None:
    """Size, bundle and framing checks: no parsing, cheap enough for the reader thread."""
    if len(dgram) < 16:
        raise OscDecodeError("short", f"{len(dgram)}-byte datagram")
    if len(dgram) > MAX_DATAGRAM:
        raise OscDecodeError("oversize", f"{len(dgram)}-byte datagram, more than {MAX_DATAGRAM}")
    if not OscBundle.dgram_is_bundle(dgram):
        raise OscDecodeError("malformed", "not an OSC bundle")
    _check_framing(dgram)


def _check_framing(dgram: bytes) -> None:
    """Every bundle element's size prefix must be a multiple of 4 and the elements must fill the
    datagram exactly (OSC 1.0, "OSC Bundles"). python-osc reads a short last element from fewer
    bytes than it announced, so a truncated datagram would otherwise decode with a wrong marker."""
    if len(dgram) % 4:
        raise OscDecodeError("short", f"{len(dgram)}-byte datagram is not a whole number of 4-byte words")
    i = 16  # "#bundle\0" and the 8-byte time tag
    while i < len(dgram):
        if i + 4 > len(dgram):
            raise OscDecodeError("short", "bundle element size cut off")
        size = int.from_bytes(dgram[i:i + 4], "big", signed=True)
        if size <= 0 or size % 4:
            raise OscDecodeError("malformed", f"bundle element size {size} is not a positive multiple of 4")
        i += 4 + size
        if i > len(dgram):
            raise OscDecodeError("short", f"bundle element of {size} bytes runs past the datagram end")


class OscSource:
    """Listen on ``host:port`` (127.0.0.1 unless told otherwise) for frame bundles.

    A reader thread drains the socket into a bounded queue at once: the kernel's UDP buffer
    holds only a few dozen 3 KB bundles, and a solver hiccup must not turn into lost frames.
    When the queue itself is full, the newest datagram is dropped and counted as ``overrun``.
    Datagrams that fail the framing checks are counted and dropped by the reader, so a flood of
    garbage cannot fill the queue and push valid frames out.
    """

    def __init__(self, host: str, port: int, labels: list[str], idle_timeout: float | None = None,
                 first_frame_timeout: float | None = None,
                 poll_s: float = 0.1, queue_size: int = 4096) -> None:
        self.labels = list(labels)
        self._where = {lab: i for i, lab in enumerate(self.labels)}
        self.idle_timeout = idle_timeout
        # senders usually start after the driver: waiting for the first frame gets its own limit
        self.first_frame_timeout = first_frame_timeout
        self.last_decode_seconds = 0.0
        self.received = 0
        self._order = FrameOrder()
        self._running = True
        self._ahead: MarkerFrame | None = None
        self._seen_good = False
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF)
        # Linux doubles the request for its bookkeeping and caps it at 2 x net.core.rmem_max
        self.rcvbuf = self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        self.sock.bind((host, port))
        self.sock.settimeout(poll_s)
        self.address = self.sock.getsockname()
        self.bad = BadInput(f"osc {host}:{self.address[1]}")
        if self.rcvbuf < RCVBUF:
            log.warning("osc %s:%d: asked the kernel for a %d KiB receive buffer, got %d KiB (datagrams beyond it "
                        "are lost and counted as missing frames); raise it with sysctl -w net.core.rmem_max=%d",
                        host, self.address[1], RCVBUF >> 10, self.rcvbuf >> 10, RCVBUF)
        self.poll_s = poll_s
        self._queue: queue.Queue[bytes] = queue.Queue(queue_size)
        self._reader = threading.Thread(target=self._read, name="osc-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while self._running:
            try:
                dgram = self.sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return  # socket closed
            try:  # cheap framing checks here, so garbage never takes a valid frame's place in the queue
                _check_datagram(dgram)
            except OscDecodeError as exc:
                self.received += 1
                self.bad.skip(exc.kind, str(exc))
                continue
            try:
                self._queue.put_nowait(dgram)
            except queue.Full:
                self.bad.skip("overrun", "receive queue full: the solver is behind the stream")

    def pending(self) -> bool:
        """True when another *valid* frame is already waiting (the pipeline then skips a stale
        frame). Garbage in the queue is decoded and counted here, never taken for a newer frame."""
        if self._ahead is None:
            self._ahead = self._next()
        return self._ahead is not None

    def _next(self, timeout: float = 0.0) -> MarkerFrame | None:
        """The next good frame received, or None (after at most ``DRAIN`` datagrams or ``timeout``)."""
        t0 = time.perf_counter()
        for _ in range(DRAIN):
            try:
                dgram = self._queue.get(timeout=timeout) if timeout else self._queue.get_nowait()
            except queue.Empty:
                return None
            self.received += 1
            frame = self.decode(dgram)
            if frame is not None:
                self.last_decode_seconds = time.perf_counter() - t0
                return frame
        return None

    @property
    def port(self) -> int:
        return self.address[1]

    def stop(self) -> None:
        self._running = False

    def close(self) -> None:
        self._running = False
        self._reader.join(timeout=2 * self.poll_s + 1)
        self.sock.close()

    def decode(self, dgram: bytes) -> MarkerFrame | None:
        try:
            frame, ts, pos, val = decode_osc_frame(dgram, self._where)
        except OscDecodeError as exc:
            self.bad.skip(exc.kind, str(exc))
            if exc.kind == "unknown_label":
                self.bad.check_labels_match(self._seen_good, str(exc))
            return None
        last, restarts = self._order.last, self._order.restarts
        if not self.bad.in_order(self._order, frame, ts):
            return None
        if last is not None and self._order.restarts == restarts and frame - last > 1:
            # UDP loses datagrams silently (a full kernel buffer, the network): say how many
            self.bad.event("missing", f"frames {last + 1}..{frame - 1} never arrived", frame - last - 1)
        self._seen_good = True
        return MarkerFrame(frame, ts, pos, val)

    def __iter__(self) -> Iterator[MarkerFrame]:
        last_good = time.monotonic()  # no frame at all ends the session after first_frame_timeout
        limit = self.first_frame_timeout if self.first_frame_timeout is not None else self.idle_timeout
        while self._running:
            frame, self._ahead = self._ahead, None
            if frame is None:
                frame = self._next(self.poll_s)
            if frame is not None:
                last_good = time.monotonic()
                limit = self.idle_timeout
                yield frame
            elif limit and time.monotonic() - last_good > limit:
                return  # checked outside the wait: a flood of garbage does not keep a dead session alive
