"""Live Link Face UDP sink: Unreal's Apple ARKit face source receives what the iPhone app sends.

Packet layout as published by the PyLiveLinkFace project (JimWest/PyLiveLinkFace,
``PyLiveLinkFace.encode``/``decode``); all values big-endian except the first:

====================  =========================================================
uint8                 packet version, 6
int32, 36 bytes       device id: length 36 (``00 00 00 24``), the bare UUID
int32                 subject name length N
N bytes               subject name, UTF-8
int32, float32        frame number, sub-frame
int32, int32          frame rate numerator, denominator
uint8                 61 (number of values)
61 x float32          52 ARKit shapes (ARKit order), head yaw/pitch/roll,
                      left eye yaw/pitch/roll, right eye yaw/pitch/roll
====================  =========================================================

PyLiveLinkFace writes the same bytes as a little-endian uint32 6 followed by ``$`` + UUID: its
``$`` is the last byte of the length 36 (0x24). The frame time is a time of day: whole frames
since midnight at numerator/denominator fps plus the sub-frame (livecap.core.timecode), so
Unreal's timecode lines up with other sources. Eye yaw and pitch come from the eye-look shapes
(livecap.core.eyes, as the VMC eye bones), eye roll is 0. The device id is derived from the actor's name,
so Unreal sees the same device every session. Head angles are relative to the actor's neutral
head pose (livecap.core.headpose). Rotations are radians. UDP, fire-and-forget: a send that
would block is dropped and counted.
"""

from __future__ import annotations

import socket
import struct
import uuid
from collections.abc import Sequence

import numpy as np

from livecap.core.headpose import NeutralWindow
from livecap.core.timecode import TimecodeClock, frame_rate_fraction, split_frames
from transport.arkit import ARKIT_NAMES, arkit_eye_yaw_pitch, arkit_matrix, head_yaw_pitch_roll

VERSION = 6
N_VALUES = 61
DEFAULT_PORT = 11111
_BODY = struct.Struct(f">ifiiB{N_VALUES}f")


def device_id(actor: str | None = None) -> str:
    """``$`` + a UUID: derived from ``actor`` (the same every session), random without one."""
    made = uuid.uuid5(uuid.NAMESPACE_URL, f"livecap:actor:{actor}") if actor is not None else uuid.uuid4()
    return "$" + str(made)


def encode_livelink(values61: np.ndarray, frame: int, subject: str = "livecap", device: str | None = None,
                    fps: int = 60, denominator: int = 1, sub_frame: float = 0.0) -> bytes:
    vals = np.asarray(values61, dtype=float)
    if vals.shape != (N_VALUES,):
        raise ValueError(f"a Live Link Face packet carries {N_VALUES} values, got {vals.shape}")
    return livelink_header(subject, device) + _body(vals.tolist(), frame, sub_frame, fps, denominator)


def livelink_header(subject: str = "livecap", device: str | None = None) -> bytes:
    """A packet's bytes before its frame time: the same for every packet of a sink."""
    dev = (device or device_id()).encode()
    if len(dev) != 37 or not dev.startswith(b"$"):
        raise ValueError(f"device id must be '$' + a 36-character UUID (the '$' is Unreal's length byte 36), "
                         f"got {dev[:40]!r}")
    name = subject.encode()
    return struct.pack("<I", VERSION) + dev + struct.pack(">i", len(name)) + name


def _body(values61: list[float], frame: int, sub_frame: float, fps: int, denominator: int) -> bytes:
    """Frame time and the 61 values as float32 (struct from Python floats: one call, no numpy per packet)."""
    return _BODY.pack(int(frame) & 0x7FFFFFFF, float(sub_frame), int(fps), int(denominator), N_VALUES, *values61)


class LiveLinkSink:
    """Send each result as one Live Link Face packet to ``host:port`` (default 127.0.0.1:11111)."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, subject: str = "livecap",
                 mapping: dict | None = None, fps: float = 60.0, where: str = "mapping", timecode: str = "clock",
                 actor: str | None = None, neutral_frames: int = 1) -> None:
        self.target = (host, port)
        self.subject = subject
        self.device = device_id(subject if actor is None else actor)
        self.mapping = mapping
        self.where = where
        self.fps, self.denominator = frame_rate_fraction(fps)
        self.clock = TimecodeClock(timecode, fps)
        self.neutral = NeutralWindow(neutral_frames)
        self.sent = 0
        self.drops = 0
        self._names: Sequence[str] | None = None
        self._M = np.zeros((len(ARKIT_NAMES), 0))
        self._same = False
        self._header = livelink_header(self.subject, self.device)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)

    def values(self, result) -> np.ndarray:
        return np.array(self._floats(result))

    def _floats(self, result) -> list[float]:
        """The 61 values in Python floats: per packet, each small numpy call costs more than its arithmetic,
        and several times more on a process just woken by the packet (docs/iphone.md, Latency)."""
        if result.names is not self._names:
            self._M = arkit_matrix(result.names, self.mapping, self.where)
            self._names = result.names
            self._same = self._M.shape == (52, 52) and np.array_equal(self._M, np.eye(52))  # ARKit in, in order
        w = result.weights if self._same else self._M @ np.asarray(result.weights, dtype=float)
        out = w.tolist() if isinstance(w, np.ndarray) else [float(v) for v in w]
        q = result.head_rotation if self.neutral.identity else self.neutral.relative(result.head_rotation,
                                                                                     result.head_translation)[0]
        left_yaw, left_pitch, right_yaw, right_pitch = arkit_eye_yaw_pitch(out)
        out += head_yaw_pitch_roll(q.tolist() if isinstance(q, np.ndarray) else [float(v) for v in q])
        out += (left_yaw, left_pitch, 0.0, right_yaw, right_pitch, 0.0)  # eye rolls stay 0
        return out

    def publish(self, result) -> None:
        tod = self.clock.seconds_of_day(result.timestamp, result.received)
        frame, sub = split_frames(tod, self.fps / self.denominator)
        pkt = self._header + _body(self._floats(result), frame, sub, self.fps, self.denominator)
        try:
            self.sock.sendto(pkt, self.target)
            self.sent += 1
        except OSError:  # would block, or ICMP port unreachable from an earlier send
            self.drops += 1

    def stats(self) -> dict:
        return {"sent": self.sent, "drops": self.drops}

    def close(self) -> None:
        self.sock.close()
