"""NatNet frames of data (message id 7), parsed with every count bounded by the bytes left.

Why not the ``natnet`` package's ``DataFrame``: it builds ``"f" * count`` from a count read off
the wire (one 20-byte force-plate channel count allocates 4.1 GB) and makes a Python object per
marker (10.6 ms for a 2400-point cloud on the 2-core AMD EPYC VM, more than a 120 Hz frame).
Here a count is checked against the packet's remaining length before anything is allocated, and
marker lists are numpy views of the datagram (no copy). The layout is the one that package reads
(natnet 0.3.0 ``data_frame.py``, the NatNet SDK's frame-of-data: prefix, marker sets, legacy
unlabelled markers, rigid bodies, skeletons >= 2.1, assets >= 4.1, labelled markers >= 2.3, force
plates >= 2.9, devices >= 2.11, suffix; from 4.1 each list's count is followed by its byte size).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

Version = tuple[int, int]

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_F32 = struct.Struct("<f")
_F64 = struct.Struct("<d")
_XYZ = np.dtype("<f4")


class NatNetPacketError(ValueError):
    """A packet that cannot be a NatNet frame: a count beyond its bytes, a string without an end."""


def labelled_dtype(version: Version) -> np.dtype:
    """One labelled marker: id, position, size, then param (>= 2.6) and residual (>= 3.0)."""
    fields = [("id", "<u4"), ("pos", "<f4", (3,)), ("size", "<f4")]
    if version >= (2, 6):
        fields.append(("param", "<u2"))
    if version >= (3, 0):
        fields.append(("residual", "<f4"))
    return np.dtype(fields)


@dataclass(frozen=True)
class NatNetFrame:
    number: int
    timestamp: float
    marker_sets: dict[str, np.ndarray]  # name -> (n, 3) float32, views of the packet
    unlabelled: np.ndarray  # the legacy "other markers", (n, 3)
    labelled: np.ndarray  # structured, labelled_dtype(version); unlabelled points have model id 0


class _Reader:
    def __init__(self, data: bytes, version: Version) -> None:
        self.data = data
        self.pos = 0
        self.version = version

    def take(self, n: int, what: str) -> int:
        if n < 0 or n > len(self.data) - self.pos:
            raise NatNetPacketError(f"{what}: needs {n} bytes, {len(self.data) - self.pos} left")
        at = self.pos
        self.pos += n
        return at

    def u16(self, what: str) -> int:
        return _U16.unpack_from(self.data, self.take(2, what))[0]

    def u32(self, what: str) -> int:
        return _U32.unpack_from(self.data, self.take(4, what))[0]

    def count(self, item_bytes: int, what: str, sized: bool = False) -> int:
        """A list's element count, refused when even its smallest elements cannot fit in what is left."""
        n = self.u32(what)
        if sized and self.version >= (4, 1):
            size = self.u32(what)
            if size > len(self.data) - self.pos:
                raise NatNetPacketError(f"{what}: claims {size} bytes, {len(self.data) - self.pos} left")
        if n * item_bytes > len(self.data) - self.pos:
            raise NatNetPacketError(f"{what}: claims {n} items, {len(self.data) - self.pos} bytes left")
        return n

    def points(self, n: int, what: str) -> np.ndarray:
        return np.frombuffer(self.data, _XYZ, 3 * n, self.take(12 * n, what)).reshape(n, 3)

    def cstring(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos, self.pos + 256)
        if end < 0:
            raise NatNetPacketError(f"{what}: name without its end within 256 bytes")
        text = self.data[self.pos:end].decode("utf-8", "replace")
        self.pos = end + 1
        return text

    def rigid_bodies(self, what: str) -> None:
        v = self.version
        fixed = 32 + (4 if v >= (2, 0) else 0) + (2 if v >= (2, 6) else 0)
        n = self.count(fixed, what, sized=True)
        if v >= (3, 0):  # marker data moved to the descriptions: fixed-size records
            self.take(n * fixed, what)
            return
        for _ in range(n):
            self.take(32, what)
            k = self.count(12 + (8 if v >= (2, 0) else 0), what)
            self.take(k * (12 + (8 if v >= (2, 0) else 0)), what)
            self.take(fixed - 32, what)

    def skeletons(self) -> None:
        for _ in range(self.count(8, "skeletons", sized=True)):
            self.take(4, "skeleton id")
            v = self.version
            fixed = 32 + (4 if v >= (2, 0) else 0) + (2 if v >= (2, 6) else 0)
            n = self.count(fixed, "skeleton rigid bodies")
            if v >= (3, 0):
                self.take(n * fixed, "skeleton rigid bodies")
            else:  # pre-3.0 rigid bodies carry their markers: walk them
                for _ in range(n):
                    self.take(32, "skeleton rigid body")
                    k = self.count(20 if v >= (2, 0) else 12, "skeleton rigid body markers")
                    self.take(k * (20 if v >= (2, 0) else 12), "skeleton rigid body markers")
                    self.take(fixed - 32, "skeleton rigid body")

    def assets(self) -> None:
        for _ in range(self.count(12, "assets", sized=True)):
            self.take(4, "asset id")
            self.take(38 * self.count(38, "asset rigid bodies"), "asset rigid bodies")
            self.take(26 * self.count(26, "asset markers"), "asset markers")

    def channels(self, what: str) -> None:
        """Force plates and devices: per item an id and channels of ``count`` floats each."""
        for _ in range(self.count(8, what, sized=True)):
            self.take(4, what)
            for _ in range(self.count(4, what)):
                self.take(4 * self.count(4, what), what)


def parse_frame(data: bytes, version: Version) -> NatNetFrame:
    """A frame of data's body (after the 4-byte message header) for a server speaking ``version``.

    Raises :class:`NatNetPacketError` (or nothing: every read is bounded by ``len(data)``)."""
    r = _Reader(bytes(data), version)
    number = r.u32("frame number")
    sets = {}
    for _ in range(r.count(5, "marker sets", sized=True)):
        name = r.cstring("marker set name")
        sets[name] = r.points(r.count(12, f"marker set {name!r}"), f"marker set {name!r}")
    unlabelled = r.points(r.count(12, "unlabelled markers", sized=True), "unlabelled markers")
    r.rigid_bodies("rigid bodies")
    if version >= (2, 1):
        r.skeletons()
    if version >= (4, 1):
        r.assets()
    dtype = labelled_dtype(version)
    labelled = np.zeros(0, dtype)
    if version >= (2, 3):
        n = r.count(dtype.itemsize, "labelled markers", sized=True)
        labelled = np.frombuffer(r.data, dtype, n, r.take(n * dtype.itemsize, "labelled markers"))
    if version >= (2, 9):
        r.channels("force plates")
    if version >= (2, 11):
        r.channels("devices")
    r.take(8, "timecode")
    if version >= (2, 7):
        timestamp = _F64.unpack_from(r.data, r.take(8, "timestamp"))[0]
    else:
        timestamp = _F32.unpack_from(r.data, r.take(4, "timestamp"))[0]
    return NatNetFrame(number, float(timestamp), sets, unlabelled, labelled)
