"""Qualisys Track Manager's real-time protocol through the ``qtm-rt`` package (Qualisys' SDK).

The client runs on its own asyncio loop in a thread; each data packet becomes a frame in a
queue. Labelled markers come from the 3D component, named by the 3D parameters' labels
(``GetParameters 3D``); unlabelled ones from the 3D-no-labels component, as a cloud. QTM sends
NaN for a labelled marker it lost.

Every packet's header is checked before ``qtm_rt`` sees it (issue 36 item 4: its receiver raised on
a size field of 0 or an unknown type, the client disconnected and the session ended with exit 0):
an unknown type, a data packet whose component table or marker counts do not fit its size, are
counted and skipped; a size that cannot be (below the 8-byte header, above ``MAX_PACKET``) loses
the stream's framing, so it is counted and the client reconnects, with backoff (0.1 s doubling to
2 s), for ``reconnect_for`` seconds; then the source is ``lost`` and ``livecap run`` exits 1.
"""

from __future__ import annotations

import asyncio
import logging
import struct
import threading
import time
import xml.etree.ElementTree as ET

import numpy as np

from livecap.core.take import MarkerFrame
from transport.capture_queue import QueuedCaptureSource, endpoint

DEFAULT_PORT = 22223  # QTM's little-endian RT port
MAX_PACKET = 16 << 20  # far above a 3D frame (16 bytes a marker); a size beyond it is a broken stream
PACKET_TYPES = range(10)  # QRTPacketType: error, command, XML, data, no more data, C3D, event, discover, QTM file, none
COMPONENT_TYPES = range(1, 20)  # QRTComponentType
MARKER_BYTES = {1: 12, 2: 16}  # 3D: x y z; 3D no labels: x y z id
_HEADER = struct.Struct("<II")
_DATA = struct.Struct("<qII")

log = logging.getLogger("livecap.input")


class QtmError(OSError):
    """QTM could not be reached or refused the stream."""


def data_problem(body: bytes) -> str | None:
    """Why a data packet's body (after the 8-byte header) cannot be read, or None. Checked before
    ``qtm_rt`` walks it: its component loop trusts the count (2^31 components of size 0 spin) and
    its marker loop the marker count."""
    if len(body) < _DATA.size:
        return f"data packet of {len(body)} bytes"
    count = _DATA.unpack_from(body)[2]
    if count * 8 > len(body) - _DATA.size:
        return f"{count} components claimed in {len(body)} bytes"
    at = _DATA.size
    for _ in range(count):
        if at + 8 > len(body):
            return f"component table runs past the packet ({len(body)} bytes)"
        size, kind = _HEADER.unpack_from(body, at)
        if size < 8 or at + size > len(body):
            return f"component of {size} bytes at {at} in {len(body)}"
        if kind not in COMPONENT_TYPES:
            return f"unknown component type {kind}"
        if kind in MARKER_BYTES:
            if size < 16:
                return f"3D component of {size} bytes"
            markers = struct.unpack_from("<I", body, at + 8)[0]
            if markers * MARKER_BYTES[kind] > size - 16:
                return f"{markers} markers claimed in a {size}-byte 3D component"
        at += size
    return None


def _guarded_protocol(source: QtmSource):
    """A ``qtm_rt`` protocol that checks each packet's header and body before its receiver parses them."""
    from qtm_rt.protocol import QTMProtocol

    class Guarded(QTMProtocol):
        def __init__(self, **kwargs) -> None:
            super().__init__(**kwargs)
            self._pending = bytearray()

        def data_received(self, data: bytes) -> None:
            self._pending += data
            while len(self._pending) >= 8:
                size, kind = _HEADER.unpack_from(self._pending)
                if not 8 <= size <= MAX_PACKET:
                    source.bad.skip("malformed", f"packet header says {size} bytes: the stream cannot be "
                                                 "followed past it; reconnecting")
                    self._pending.clear()
                    if self.transport is not None:
                        self.transport.close()
                    return
                if len(self._pending) < size:
                    return
                packet = bytes(self._pending[:size])
                del self._pending[:size]
                problem = (f"unknown packet type {kind}" if kind not in PACKET_TYPES
                           else data_problem(packet[8:]) if kind == 3 else None)
                if problem:
                    source.bad.skip("malformed", problem)
                    continue
                try:
                    self._receiver.data_received(packet)
                except Exception as exc:  # the package's parsers: count, forget the packet, go on
                    self._receiver._received_data = b""
                    source.bad.skip("malformed", f"unreadable QTM packet ({type(exc).__name__}: {exc})")

    return Guarded


def labels_from_parameters(xml: bytes | str) -> list[str]:
    """Marker names from a ``GetParameters 3D`` reply, in the 3D component's order."""
    root = ET.fromstring(xml)
    return [(e.findtext("Name") or "").strip() for e in root.iter("Label")]


class QtmSource(QueuedCaptureSource):
    """Frames from QTM. ``labels`` (the session's order) with ``unlabelled=False`` streams the 3D
    component mapped onto them; ``unlabelled=True`` streams 3D-no-labels as clouds."""

    def __init__(self, host: str, port: int = DEFAULT_PORT, labels: list[str] | None = None,
                 unlabelled: bool = False, timeout: float = 5.0, idle_timeout: float | None = None,
                 version: str = "1.25", reconnect_for: float = 10.0) -> None:
        import qtm_rt  # noqa: F401  (fail here, in the caller's thread, when the package is absent)

        self.host, self.port = host, port
        self.unlabelled = unlabelled or labels is None
        self.labels = None if self.unlabelled else list(labels)
        self.reconnect_for = reconnect_for
        self.reconnects = 0
        self._start_queue(f"qtm {endpoint(host, port)}", idle_timeout)
        self.stream_labels: list[str] = []
        self._ready = threading.Event()
        self._error: str | None = None
        self._loop = asyncio.new_event_loop()
        self._stop_future: asyncio.Future | None = None
        self._thread = threading.Thread(target=self._run, args=(version, timeout), daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout + 1.0) or self._error:
            self.close()
            raise QtmError(f"QTM at {endpoint(host, port)}: {self._error or 'no answer'}")

    # ------------------------------------------------------------------ client thread
    def _run(self, version: str, timeout: float) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._serve(version, timeout))
        except Exception as exc:  # the session ends; the consumer sees it through _error
            self._error = f"{type(exc).__name__}: {exc}"
        finally:
            self._ready.set()
            self._queue.put(None)

    async def _serve(self, version: str, timeout: float) -> None:
        """The first session (its errors go to the constructor), then reconnects while the source runs."""
        if not await self._session(version, timeout):
            return
        delay, lost_at = 0.1, time.monotonic()
        while self._running:
            self.lost = f"QTM at {endpoint(self.host, self.port)}: connection lost"
            if time.monotonic() - lost_at > self.reconnect_for:
                self.lost += f", no answer for {self.reconnect_for:g} s"
                return
            await asyncio.sleep(delay)
            delay = min(2 * delay, 2.0)
            if not self._running:
                return
            try:
                streamed = await self._session(version, timeout)
            except Exception as exc:  # refused, reset, timed out: try again after the backoff
                log.warning("qtm %s: reconnect failed (%s: %s)", endpoint(self.host, self.port), type(exc).__name__,
                            exc)
                continue
            if streamed:  # it streamed again, then was lost again: a fresh backoff
                delay, lost_at = 0.1, time.monotonic()

    async def _session(self, version: str, timeout: float) -> bool:
        """Connect, stream until the connection drops or the source stops; True once it streamed."""
        from qtm_rt.qrt import QRTConnection

        self._error = None
        try:
            _, protocol = await asyncio.wait_for(self._loop.create_connection(
                lambda: _guarded_protocol(self)(loop=self._loop, on_disconnect=lambda *_: self._finish()),
                self.host, self.port), timeout)
        except (TimeoutError, OSError) as exc:
            self._error = f"cannot connect ({type(exc).__name__})"
            return False
        conn = QRTConnection(protocol, timeout=timeout)
        self._stop_future = self._loop.create_future()
        try:
            await asyncio.wait_for(protocol.set_version(version), timeout)
            if not self.unlabelled:
                self.stream_labels = labels_from_parameters(await conn.get_parameters(parameters=["3d"]))
                where = {lab: i for i, lab in enumerate(self.stream_labels)}
                self._map = np.array([where.get(lab, -1) for lab in self.labels])
                if (self._map < 0).all():
                    self._error = (f"none of the session's labels among QTM's "
                                   f"({', '.join(self.stream_labels[:5])}...)")
                    conn.disconnect()
                    return False
            await conn.stream_frames(components=["3dnolabels" if self.unlabelled else "3d"],
                                     on_packet=self._hand_over)
        except BaseException:  # a half-open session: close it before the next try
            if conn.has_transport():
                conn.disconnect()
            raise
        if self.lost:
            self.reconnects += 1
            log.warning("qtm %s: reconnected (%d)", endpoint(self.host, self.port), self.reconnects)
            self.lost = None
        self._ready.set()
        await self._stop_future
        if conn.has_transport():
            try:
                await conn.stream_frames_stop()
            except Exception:
                pass
            conn.disconnect()
        return True

    def _finish(self) -> None:
        if self._stop_future is not None and not self._stop_future.done():
            self._stop_future.set_result(None)

    def decode(self, packet) -> MarkerFrame | None:
        """One data packet (its components checked by ``data_problem``) to a frame, or None (counted)."""
        kind = 2 if self.unlabelled else 1
        at = next((at for c, at in packet.components.items() if c.value == kind), None)
        if at is None:
            self.bad.skip("malformed", f"frame {packet.framenumber}: no 3D component")
            return None
        count = struct.unpack_from("<I", packet.data, at)[0]
        width = MARKER_BYTES[kind] // 4
        pts = np.frombuffer(packet.data, "<f4", count * width, at + 8).reshape(count, width)[:, :3]
        pts = pts.astype(np.float64)
        order = self._order.check(packet.framenumber)
        if order:
            self.bad.skip(order, f"frame {packet.framenumber} after {self._order.last}")
            return None
        ts = packet.timestamp * 1e-6
        valid = np.isfinite(pts).all(1)
        if self.unlabelled:
            return MarkerFrame(packet.framenumber, ts, np.where(valid[:, None], pts, 0.0), valid)
        if len(pts) != len(self.stream_labels):
            self.bad.skip("malformed", f"frame {packet.framenumber}: {len(pts)} markers, "
                                       f"{len(self.stream_labels)} labels")
            return None
        has = self._map >= 0
        pos = np.zeros((len(self.labels), 3))
        ok = np.zeros(len(self.labels), dtype=bool)
        pos[has] = pts[self._map[has]]
        ok[has] = valid[self._map[has]]
        return MarkerFrame(packet.framenumber, ts, np.where(ok[:, None], pos, 0.0), ok)

    # ------------------------------------------------------------------ consumer
    def close(self) -> None:
        self._running = False
        if self._loop.is_running():
            self._loop.call_soon_threadsafe(self._finish)
        self._thread.join(timeout=3.0)
