"""Versioned wire formats for markers in and weights out over ZeroMQ, and their decoders.

ZeroMQ messages are multipart ``[topic, msgpack payload]`` (the style of Pupil Labs' network
API). Topics: ``markers.<actor>`` in, ``weights.<actor>`` out. Every payload is a msgpack map
with ``"v"`` (the wire version, :data:`WIRE_VERSION`) and ``"type"``. Arrays travel as raw
little-endian float32 bytes, so a frame of 60 markers is ~1 KB and decodes without a Python
loop. docs/protocol.md has the byte-level description with worked examples.

Decoders raise :class:`WireError` subclasses whose ``kind`` names the counter a running session
bumps (short, malformed, version, nonfinite, unknown_label, duplicate_label, unknown_layout);
they never raise anything else on bytes from the network.
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import msgpack
import numpy as np

WIRE_VERSION = 1
MAX_MARKERS = 4096  # a sanity bound: anything bigger is a malformed packet, not a face
# Largest marker message accepted: 4096 markers with 64-character labels fit in ~330 KB.
MAX_MESSAGE_BYTES = 1 << 20
LAYOUT_TABLE_SIZE = 16  # layouts remembered per source (LRU); at most 16 x 4096 x 128 characters
MAX_LABEL_CHARS = 128
# Every payload is a msgpack map (msgpack spec: fixmap 0x80-0x8f, map16 0xde, map32 0xdf): the first
# byte rejects ~85 % of random garbage before msgpack runs, on the thread that solves frames.
_MAP_FIRST_BYTES = frozenset([*range(0x80, 0x90), 0xDE, 0xDF])


class WireError(ValueError):
    """A packet that cannot be used; ``kind`` is the bad-input counter it belongs to."""

    kind = "malformed"


class ShortPacket(WireError):
    kind = "short"


class MalformedPacket(WireError):
    kind = "malformed"


class WrongVersion(WireError):
    kind = "version"


class NonFinite(WireError):
    kind = "nonfinite"


class UnknownLabel(WireError):
    kind = "unknown_label"


class DuplicateLabel(WireError):
    kind = "duplicate_label"


class UnknownLayout(WireError):
    kind = "unknown_layout"


class LayoutMismatch(WireError):
    kind = "layout_mismatch"


class Oversize(WireError):
    kind = "oversize"


class LayoutTable(OrderedDict):
    """Layout id -> labels, least recently used first, at most ``size`` entries: a sender
    announcing a new layout per packet cannot grow the receiver's memory.

    ``pin`` the session's own layout and mark the one the last good frame used ``active``: neither
    is evicted, so a burst of fresh layouts cannot make the honest stream's id-only packets
    unknown, whatever its label order. With ``allowed`` (the
    session's labels), a layout naming any other label is refused before it is learned; its id
    is remembered (bounded) so the sender's id-only packets count as ``unknown_label`` too, which
    is what tells a wrong --profile from a lost announcement."""

    def __init__(self, size: int = LAYOUT_TABLE_SIZE, allowed: Sequence[str] | None = None) -> None:
        super().__init__()
        self.size = size
        self.allowed = None if allowed is None else frozenset(allowed)
        self.pinned: set[str] = set()
        self.active: str | None = None
        self.refused: OrderedDict[str, list[str]] = OrderedDict()  # id -> a few of its foreign labels

    def pin(self, labels: Sequence[str]) -> str:
        lid = layout_id(labels)
        self.pinned.add(lid)
        self.learn(lid, list(labels))
        return lid

    def get_labels(self, lid: str) -> list[str] | None:
        labels = self.get(lid)
        if labels is not None:
            self.move_to_end(lid)
        return labels

    def foreign(self, labels: list[str]) -> list[str]:
        """The labels (at most 5) the session does not have; empty when every label is allowed."""
        if self.allowed is None:
            return []
        return [s for s in labels if s not in self.allowed][:5]

    def refuse(self, lid: str, foreign: list[str]) -> None:
        self.refused[lid] = foreign
        self.refused.move_to_end(lid)
        if len(self.refused) > self.size:
            self.refused.popitem(last=False)

    def learn(self, lid: str, labels: list[str]) -> None:
        self[lid] = labels
        self.move_to_end(lid)
        if len(self) > self.size:
            for old in [k for k in self if k not in self.pinned and k != self.active][:len(self) - self.size]:
                del self[old]


def layout_id(labels: Sequence[str]) -> str:
    """A short id for an ordered label list: both ends can compute it, so after the first
    frame a sender may omit the labels and the receiver still knows them."""
    return hashlib.sha1("\n".join(labels).encode()).hexdigest()[:16]


def topic(kind: str, actor: str) -> bytes:
    return f"{kind}.{actor}".encode()


# ---------------------------------------------------------------------------------- markers
@dataclass
class MarkerPacket:
    frame: int
    timestamp: float
    labels: list[str]
    positions: np.ndarray  # n x 3 float64, mm; 0 where not valid
    valid: np.ndarray  # n bool
    layout: str | None = None  # the layout id the packet named, if any


def encode_markers(frame: int, timestamp: float, positions: np.ndarray, valid: np.ndarray,
                   labels: Sequence[str] | None = None, layout: str | None = None) -> bytes:
    """Payload of a ``markers.<actor>`` message. Give ``labels`` (and optionally register them
    under ``layout``) or only ``layout`` for a label list the receiver already knows."""
    if labels is None and layout is None:
        raise ValueError("a marker packet needs labels or a layout id")
    pos = np.asarray(positions, dtype="<f4").reshape(-1, 3)
    val = np.asarray(valid, dtype=bool).reshape(-1)
    msg: dict = {"v": WIRE_VERSION, "type": "markers", "frame": int(frame), "timestamp": float(timestamp),
                 "positions": pos.tobytes(), "valid": val.astype(np.uint8).tobytes()}
    if labels is not None:
        msg["labels"] = list(labels)
    if layout is not None:
        msg["layout"] = layout
    return msgpack.packb(msg, use_bin_type=True)


def _unpack_map(payload: bytes, expected_type: str) -> dict:
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise MalformedPacket("payload is not bytes")
    if len(payload) == 0:
        raise ShortPacket("empty payload")
    if len(payload) > MAX_MESSAGE_BYTES:
        raise Oversize(f"{len(payload)}-byte payload, more than {MAX_MESSAGE_BYTES}")
    if payload[0] not in _MAP_FIRST_BYTES:  # most garbage, refused at a fraction of an unpack's cost
        raise MalformedPacket(f"payload starts with byte 0x{payload[0]:02x}, not a msgpack map")
    try:
        msg = msgpack.unpackb(payload, raw=False, strict_map_key=False, max_bin_len=1 << 24, max_str_len=1 << 16,
                              max_array_len=1 << 16, max_map_len=64)
    except (msgpack.exceptions.ExtraData, ValueError, TypeError) as exc:
        text = str(exc).lower()
        if "insufficient" in text or "incomplete" in text or isinstance(exc, msgpack.exceptions.OutOfData):
            raise ShortPacket(f"truncated msgpack ({exc})") from None
        raise MalformedPacket(f"not msgpack ({exc})") from None
    except Exception as exc:  # msgpack raises a few private exception types on hostile input
        raise MalformedPacket(f"not msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(msg, dict):
        raise MalformedPacket(f"payload is a msgpack {type(msg).__name__}, not a map")
    v = msg.get("v")
    if not isinstance(v, int) or isinstance(v, bool):
        raise MalformedPacket("no integer version field 'v'")
    if v != WIRE_VERSION:
        raise WrongVersion(f"wire version {v}, this build speaks {WIRE_VERSION}")
    if msg.get("type") != expected_type:
        raise MalformedPacket(f"type {msg.get('type')!r}, expected {expected_type!r}")
    return msg


def _number(msg: dict, key: str, kind: type) -> float | int:
    val = msg.get(key)
    ok = isinstance(val, int) and not isinstance(val, bool) if kind is int else isinstance(val, int | float)
    if not ok or isinstance(val, bool):
        raise MalformedPacket(f"field {key!r} missing or not a number")
    if kind is int and not -(2**62) < val < 2**62:
        raise MalformedPacket(f"field {key!r} out of range")
    return val


def decode_markers(payload: bytes, layouts: dict[str, list[str]] | None = None) -> MarkerPacket:
    """Decode and check one marker payload. ``layouts`` (id -> labels) is consulted for packets
    that carry only a layout id, and learns the labels of packets that carry both, once the id
    is checked to be the hash of those labels (a wrong id would re-order every later frame)."""
    msg = _unpack_map(payload, "markers")
    frame = int(_number(msg, "frame", int))
    timestamp = float(_number(msg, "timestamp", float))
    if not math.isfinite(timestamp):
        raise NonFinite("timestamp is not finite")
    labels = msg.get("labels")
    lid = msg.get("layout")
    if lid is not None and not isinstance(lid, str):
        raise MalformedPacket("layout id is not a string")
    if labels is None:
        if lid is None:
            raise MalformedPacket("neither labels nor a layout id")
        known = None
        if layouts is not None:
            known = layouts.get_labels(lid) if isinstance(layouts, LayoutTable) else layouts.get(lid)
        if known is None:
            if isinstance(layouts, LayoutTable) and lid in layouts.refused:
                raise UnknownLabel(f"layout {lid!r} was refused: unknown labels {layouts.refused[lid]}")
            raise UnknownLayout(f"layout id {lid!r} was never announced with its labels")
        labels = known
    else:
        if not isinstance(labels, list) or not all(isinstance(s, str) for s in labels):
            raise MalformedPacket("labels is not a list of strings")
        if len(labels) > MAX_MARKERS:
            raise MalformedPacket(f"{len(labels)} labels is more than {MAX_MARKERS}")
        if any(len(s) > MAX_LABEL_CHARS for s in labels):
            raise MalformedPacket(f"a label is longer than {MAX_LABEL_CHARS} characters")
        if len(set(labels)) != len(labels):
            seen: set[str] = set()
            dup = next(s for s in labels if s in seen or seen.add(s))
            raise DuplicateLabel(f"label {dup!r} appears twice")
        if lid is not None:
            if lid != layout_id(labels):
                raise LayoutMismatch(f"layout id {lid!r} is not the id of the labels sent with it "
                                     f"({layout_id(labels)!r})")
            if isinstance(layouts, LayoutTable):
                if lid not in layouts:
                    foreign = layouts.foreign(labels)
                    if foreign:  # refused before it is learned: it can neither evict nor be used
                        layouts.refuse(lid, foreign)
                        raise UnknownLabel(f"layout {lid!r} names markers the session lacks: unknown labels {foreign}")
                layouts.learn(lid, layouts.get(lid) or list(labels))
            elif layouts is not None:
                layouts[lid] = list(labels)
    n = len(labels)
    pos = msg.get("positions")
    val = msg.get("valid", None)
    if not isinstance(pos, bytes):
        raise MalformedPacket("positions is not a byte string")
    if len(pos) < 12 * n:
        raise ShortPacket(f"positions hold {len(pos)} bytes, {n} markers need {12 * n}")
    if len(pos) != 12 * n:
        raise MalformedPacket(f"positions hold {len(pos)} bytes, {n} markers need {12 * n}")
    positions = np.frombuffer(pos, dtype="<f4").reshape(n, 3).astype(np.float64)
    if val is None:
        valid = np.ones(n, dtype=bool)
    elif not isinstance(val, bytes):
        raise MalformedPacket("valid is not a byte string")
    elif len(val) < n:
        raise ShortPacket(f"valid mask holds {len(val)} bytes for {n} markers")
    elif len(val) != n:
        raise MalformedPacket(f"valid mask holds {len(val)} bytes for {n} markers")
    else:
        valid = np.frombuffer(val, dtype=np.uint8) != 0
        if not valid.all():
            positions[~valid] = 0.0
    # one reduction instead of a mask and a test per coordinate: float32 values summed in float64 cannot
    # overflow (4096 x 3 x 3.4e38), so the sum is finite exactly when every coordinate left is
    if not math.isfinite(positions.sum()):
        raise NonFinite("a marker flagged valid has a NaN or infinite coordinate")
    return MarkerPacket(frame, timestamp, list(labels), positions, valid, lid)


# ---------------------------------------------------------------------------------- weights
def encode_header(names: Sequence[str], actor: str, rate: float | None = None) -> bytes:
    """The shape-name header of a ``weights.<actor>`` stream (re-sent periodically and on join)."""
    msg = {"v": WIRE_VERSION, "type": "header", "actor": actor, "names": list(names),
           "names_id": layout_id(names), "rate": float(rate) if rate else 0.0}
    return msgpack.packb(msg, use_bin_type=True)


def encode_weights(result, names_id: str) -> bytes:
    """Payload of one ``weights.<actor>`` frame from a :class:`livecap.core.result.SolveResult`."""
    msg = {
        "v": WIRE_VERSION, "type": "weights", "frame": int(result.frame), "timestamp": float(result.timestamp),
        "names_id": names_id, "weights": np.asarray(result.weights, dtype="<f4").tobytes(),
        "head_rotation": np.asarray(result.head_rotation, dtype=np.float64).tolist(),
        "head_translation": np.asarray(result.head_translation, dtype=np.float64).tolist(),
        "residual": float(result.residual), "solve_time": float(result.solve_time),
    }
    if result.valid is not None:
        msg["markers"], msg["valid"] = int(len(result.valid)), int(np.count_nonzero(result.valid))
    if result.at_bound is not None:
        msg["at_bound"] = np.asarray(result.at_bound, dtype=np.int8).tobytes()
    return msgpack.packb(msg, use_bin_type=True)


@dataclass
class WeightsPacket:
    frame: int
    timestamp: float
    names_id: str
    weights: np.ndarray  # m float32 -> float64
    head_rotation: np.ndarray  # 4 (x, y, z, w)
    head_translation: np.ndarray  # 3 mm
    residual: float
    solve_time: float
    valid: int | None = None  # markers seen this frame (of ``markers``)
    markers: int | None = None
    at_bound: np.ndarray | None = None  # m int8: -1 at the lower limit, +1 at the upper, 0 inside


def decode_payload(payload: bytes):
    """A decoded ``weights.<actor>`` payload: a header dict or a :class:`WeightsPacket`."""
    try:
        msg = _unpack_map(payload, "weights")
    except MalformedPacket:
        msg = _unpack_map(payload, "header")
        names = msg.get("names")
        if not isinstance(names, list) or not all(isinstance(s, str) for s in names):
            raise MalformedPacket("header names is not a list of strings") from None
        return msg
    w = msg.get("weights")
    if not isinstance(w, bytes) or len(w) % 4:
        raise MalformedPacket("weights is not float32 bytes")
    rot, tr = msg.get("head_rotation"), msg.get("head_translation")
    if not (isinstance(rot, list) and len(rot) == 4 and isinstance(tr, list) and len(tr) == 3):
        raise MalformedPacket("head pose has the wrong shape")
    return WeightsPacket(int(_number(msg, "frame", int)), float(_number(msg, "timestamp", float)),
                         str(msg.get("names_id")), np.frombuffer(w, dtype="<f4").astype(np.float64),
                         np.asarray(rot, dtype=float), np.asarray(tr, dtype=float),
                         float(msg.get("residual", 0.0)), float(msg.get("solve_time", 0.0)),
                         *_quality(msg, len(w) // 4))


def _quality(msg: dict, m: int) -> tuple[int | None, int | None, np.ndarray | None]:
    """The optional solve-quality keys (valid, markers, at_bound); absent ones are None."""
    counts = [msg.get(k) for k in ("valid", "markers")]
    if any(c is not None and (not isinstance(c, int) or c < 0) for c in counts):
        raise MalformedPacket("valid / markers are not counts")
    b = msg.get("at_bound")
    if b is not None and (not isinstance(b, bytes) or len(b) != m):
        raise MalformedPacket("at_bound is not one int8 per weight")
    return counts[0], counts[1], None if b is None else np.frombuffer(b, dtype=np.int8).copy()
