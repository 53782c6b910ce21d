"""Qualisys Track Manager's real-time protocol through the ``qtm-rt`` package (Qualisys' SDK).

The client runs on its own asyncio loop in a thread; each data packet becomes a frame in a
queue. Labelled markers come from the 3D component, named by the 3D parameters' labels
(``GetParameters 3D``); unlabelled ones from the 3D-no-labels component, as a cloud. QTM sends
NaN for a labelled marker it lost. A packet whose components cannot be read (short, wrong
counts) is counted and skipped.
"""

from __future__ import annotations

import asyncio
import struct
import threading
import xml.etree.ElementTree as ET

import numpy as np

from livecap.core.take import MarkerFrame
from transport.capture_queue import QueuedCaptureSource

DEFAULT_PORT = 22223  # QTM's little-endian RT port


class QtmError(OSError):
    """QTM could not be reached or refused the stream."""


def labels_from_parameters(xml: bytes | str) -> list[str]:
    """Marker names from a ``GetParameters 3D`` reply, in the 3D component's order."""
    root = ET.fromstring(xml)
    return [(e.findtext("Name") or "").strip() for e in root.iter("Label")]


class QtmSource(QueuedCaptureSource):
    """Frames from QTM. ``labels`` (the session's order) with ``unlabelled=False`` streams the 3D
    component mapped onto them; ``unlabelled=True`` streams 3D-no-labels as clouds."""

    def __init__(self, host: str, port: int = DEFAULT_PORT, labels: list[str] | None = None,
                 unlabelled: bool = False, timeout: float = 5.0, idle_timeout: float | None = None,
                 version: str = "1.25") -> None:
        import qtm_rt  # noqa: F401  (fail here, in the caller's thread, when the package is absent)

        self.host, self.port = host, port
        self.unlabelled = unlabelled or labels is None
        self.labels = None if self.unlabelled else list(labels)
        self._start_queue(f"qtm {host}:{port}", idle_timeout)
        self.stream_labels: list[str] = []
        self._ready = threading.Event()
        self._error: str | None = None
        self._loop = asyncio.new_event_loop()
        self._stop_future: asyncio.Future | None = None
        self._thread = threading.Thread(target=self._run, args=(version, timeout), daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout + 1.0) or self._error:
            self.close()
            raise QtmError(f"QTM at {host}:{port}: {self._error or 'no answer'}")

    # ------------------------------------------------------------------ client thread
    def _run(self, version: str, timeout: float) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._session(version, timeout))
        except Exception as exc:  # the session ends; the consumer sees it through _error
            self._error = f"{type(exc).__name__}: {exc}"
        finally:
            self._ready.set()
            self._queue.put(None)

    async def _session(self, version: str, timeout: float) -> None:
        import qtm_rt

        conn = await qtm_rt.connect(self.host, self.port, version=version, timeout=timeout,
                                    on_disconnect=lambda *_: self._finish())
        if conn is None:
            self._error = "cannot connect"
            return
        if not self.unlabelled:
            self.stream_labels = labels_from_parameters(await conn.get_parameters(parameters=["3d"]))
            where = {lab: i for i, lab in enumerate(self.stream_labels)}
            self._map = np.array([where.get(lab, -1) for lab in self.labels])
            if (self._map < 0).all():
                self._error = f"none of the session's labels among QTM's ({', '.join(self.stream_labels[:5])}...)"
                conn.disconnect()
                return
        self._stop_future = self._loop.create_future()
        await conn.stream_frames(components=["3dnolabels" if self.unlabelled else "3d"], on_packet=self._hand_over)
        self._ready.set()
        await self._stop_future
        if conn.has_transport():
            try:
                await conn.stream_frames_stop()
            except Exception:
                pass
            conn.disconnect()

    def _finish(self) -> None:
        if self._stop_future is not None and not self._stop_future.done():
            self._stop_future.set_result(None)

    def decode(self, packet) -> MarkerFrame | None:
        """One data packet to a frame, or None (counted) when it cannot be read."""
        try:
            if self.unlabelled:
                got = packet.get_3d_markers_no_label()
            else:
                got = packet.get_3d_markers()
            if got is None:
                self.bad.skip("malformed", f"frame {packet.framenumber}: no 3D component")
                return None
            _, markers = got
            pts = np.array([m[:3] for m in markers], dtype=np.float64).reshape(-1, 3)
        except (struct.error, ValueError, KeyError) as exc:
            self.bad.skip("malformed", f"unreadable data packet ({exc})")
            return None
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
