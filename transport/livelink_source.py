"""Live Link Face UDP source: the iPhone app's ARKit weights and head angles, as solved frames.

The app's packet (the layout transport/livelink.py writes; docs/protocol.md, Live Link)::

    uint8 version (6) | int32 id length L | L bytes device id | int32 name length N | N bytes subject
    | int32 frame | float32 sub-frame | int32 fps numerator | int32 denominator | uint8 count | count x float32

all big-endian. The device id is length-prefixed, so it is read by its length, not assumed to be a
36-byte UUID: the real packets in ../shared/realdata/performance/dao.gesichter carry a 32-byte id,
which PyLiveLinkFace (fixed offsets) cannot decode. ``count`` is 61 (52 shapes + head and eye
angles) or 52 (shapes only: the angles read 0). Other versions are counted as ``version``.

The frame time is the packet's time of day (frames / fps + sub-frame), so timecode is kept. A new
device id, or frame numbers jumping back, is a sender that restarted: counted as
``stream_restart`` and followed. The weights need no solve; each packet becomes a
:class:`~livecap.core.result.SolveResult` of the 52 ARKit shapes with the head rotation of its angles.
"""

from __future__ import annotations

import math
import socket
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from livecap.core.result import SolveResult
from transport.arkit import ARKIT_NAMES
from transport.badinput import BadInput, FrameOrder

VERSIONS = (6,)
COUNTS = (52, 61)
MAX_ID = 256  # bytes: a device id or subject longer than this is not the app's
MAX_DATAGRAM = 2048
_TIME = struct.Struct(">ifiiB")  # frame, sub-frame, fps numerator, denominator, value count
_VALUES = {n: struct.Struct(f">{n}f") for n in COUNTS}
_NO_ANGLES = (0.0,) * (61 - 52)


class LiveLinkDecodeError(ValueError):
    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(detail)
        self.kind = kind


@dataclass
class LiveLinkPacket:
    device: str
    subject: str
    frame: int
    sub_frame: float
    fps: int
    denominator: int
    floats: tuple[float, ...]  # 61: 52 ARKit weights, head yaw/pitch/roll, left eye, right eye (radians)

    @property
    def values(self) -> np.ndarray:
        """The 61 values as an array (the live path reads :attr:`floats`: no numpy call per packet)."""
        return np.array(self.floats)

    @property
    def seconds(self) -> float:
        """Time of day: whole frames at fps/denominator plus the sub-frame."""
        return (self.frame + self.sub_frame) * self.denominator / self.fps


def decode_livelink(dgram: bytes) -> LiveLinkPacket:
    """One packet; raises :class:`LiveLinkDecodeError` carrying the bad-input kind."""
    if len(dgram) < 1 + 4 + 4 + 17 + 52 * 4:
        raise LiveLinkDecodeError("short", f"{len(dgram)}-byte datagram")
    if len(dgram) > MAX_DATAGRAM:
        raise LiveLinkDecodeError("oversize", f"{len(dgram)}-byte datagram, more than {MAX_DATAGRAM}")
    if dgram[0] not in VERSIONS:
        raise LiveLinkDecodeError("version", f"Live Link packet version {dgram[0]}, this build reads {VERSIONS}")
    i = 1
    texts = []
    for what in ("device id", "subject"):
        (n,) = struct.unpack_from(">i", dgram, i)
        if not 0 <= n <= MAX_ID or i + 4 + n > len(dgram):
            raise LiveLinkDecodeError("malformed", f"{what} length {n}")
        try:
            texts.append(dgram[i + 4:i + 4 + n].decode("utf-8"))
        except UnicodeDecodeError:
            raise LiveLinkDecodeError("malformed", f"{what} is not UTF-8") from None
        i += 4 + n
    if i + 17 > len(dgram):
        raise LiveLinkDecodeError("short", "frame time cut off")
    frame, sub, fps, den, count = _TIME.unpack_from(dgram, i)
    i += 17
    if count not in COUNTS:
        raise LiveLinkDecodeError("malformed", f"{count} values, the app sends {COUNTS}")
    if len(dgram) != i + 4 * count:
        kind = "short" if len(dgram) < i + 4 * count else "malformed"
        raise LiveLinkDecodeError(kind, f"{len(dgram)} bytes, {count} values need {i + 4 * count}")
    if fps <= 0 or den <= 0 or frame < 0:
        raise LiveLinkDecodeError("malformed", f"frame {frame} at {fps}/{den} fps")
    # Python floats, not numpy: woken once per packet, numpy's cast and reduction cost ~10x their warm time
    values = _VALUES[count].unpack_from(dgram, i)
    if not math.isfinite(sum(values) + sub):  # NaN or inf anywhere survives the sum (no float32 overflows it)
        raise LiveLinkDecodeError("nonfinite", "a value is NaN or infinite")
    return LiveLinkPacket(texts[0], texts[1], frame, sub, fps, den, values if count == 61 else values + _NO_ANGLES)


def head_quaternion(yaw_pitch_roll: np.ndarray) -> np.ndarray:
    """The rotation (x, y, z, w) whose :func:`transport.arkit.head_angles` are these angles:
    intrinsic Y, X, Z, i.e. Ry(yaw) Rx(pitch) Rz(roll)."""
    yaw, pitch, roll = yaw_pitch_roll
    a, b, c = 0.5 * float(yaw), 0.5 * float(pitch), 0.5 * float(roll)  # floats: per packet (docs/iphone.md, Latency)
    sy, cy, sx, cx, sz, cz = math.sin(a), math.cos(a), math.sin(b), math.cos(b), math.sin(c), math.cos(c)
    x, y, z, w = cy * sx, sy * cx, -sy * sx, cy * cx  # (0, sy, 0, cy) (sx, 0, 0, cx), Hamilton's product
    return np.array([x * cz + y * sz, y * cz - x * sz, w * sz + z * cz, w * cz - z * sz])  # then (0, 0, sz, cz)


class LiveLinkFaceSource:
    """Listen on ``host:port`` for the app's packets; iterate :class:`SolveResult` (ARKit names)."""

    def __init__(self, host: str, port: int, idle_timeout: float | None = None,
                 first_frame_timeout: float | None = None, poll_s: float = 0.1) -> None:
        self.idle_timeout = idle_timeout
        self.first_frame_timeout = first_frame_timeout
        self.poll_s = poll_s
        self.names = list(ARKIT_NAMES)
        self.received = 0
        self.last_decode_seconds = 0.0
        self.device: str | None = None
        self._order = FrameOrder()
        self._running = True
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.sock.bind((host, port))
        # the kernel's receive timeout on a blocking socket, not settimeout's, which polls before every recv (one
        # more system call per packet); a wait with no packet raises BlockingIOError. 0 would mean "forever".
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO,
                             struct.pack("ll", *divmod(max(1, round(poll_s * 1e6)), 1_000_000)))
        self.address = self.sock.getsockname()
        self.bad = BadInput(f"livelink {host}:{self.address[1]}")

    @property
    def port(self) -> int:
        return self.address[1]

    def decode(self, dgram: bytes) -> SolveResult | None:
        """The packet as a result, or None (counted in :attr:`bad`)."""
        try:
            pkt = decode_livelink(dgram)
        except LiveLinkDecodeError as exc:
            self.bad.skip(exc.kind, str(exc))
            return None
        if pkt.device != self.device:
            if self.device is not None:
                self.bad.event("stream_restart", f"device {pkt.device!r} after {self.device!r}: following it")
                self._order = FrameOrder()
            self.device = pkt.device
        if not self.bad.in_order(self._order, pkt.frame, pkt.seconds):
            return None
        return SolveResult(pkt.frame, pkt.seconds, self.names, np.array(pkt.floats[:52]),
                           head_quaternion(pkt.floats[52:55]), np.zeros(3))

    def stop(self) -> None:
        self._running = False

    def close(self) -> None:
        self._running = False
        self.sock.close()

    def __iter__(self) -> Iterator[SolveResult]:
        last_good = time.monotonic()
        limit = self.first_frame_timeout if self.first_frame_timeout is not None else self.idle_timeout
        while self._running:
            try:
                dgram = self.sock.recv(65536)
            except BlockingIOError:  # SO_RCVTIMEO passed without a packet
                dgram = None
            except OSError:
                return  # closed
            if dgram is not None:
                t0 = time.perf_counter()
                self.received += 1
                result = self.decode(dgram)
                if result is not None:
                    self.last_decode_seconds = time.perf_counter() - t0
                    last_good = time.monotonic()
                    limit = self.idle_timeout
                    yield result
                    continue
            if limit and time.monotonic() - last_good > limit:
                return
