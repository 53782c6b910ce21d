"""OptiTrack NatNet (Motive's streaming protocol) through the ``natnet`` package, unicast.

The package parses frames of data and data descriptions; this module drives it from its own
thread (``update_sync`` after a ``select`` on the command socket, where a unicast server sends
everything) so that one malformed packet is counted and skipped instead of ending the package's
receive thread. Labelled markers: one marker set (``marker_set``, or the first holding the
session's labels) named by the data descriptions. Unlabelled: every marker of the frame's
labelled-marker list that is not occluded (Motive puts unlabelled points there, model id 0), or
the legacy "other markers" list when that one is empty. Motive streams metres by default.
"""

from __future__ import annotations

import select
import struct
import threading
import time

import numpy as np

from livecap.core.take import MarkerFrame
from livecap.core.units import MM_PER_UNIT
from transport.capture import QueuedCaptureSource

DEFAULT_PORT = 1510  # Motive's command port


class NatNetSourceError(OSError):
    """No NatNet server answered, or it has no marker set for the session's labels."""


class NatNetSource(QueuedCaptureSource):
    def __init__(self, server: str, port: int = DEFAULT_PORT, labels: list[str] | None = None,
                 unlabelled: bool = False, marker_set: str | None = None, units: str = "m",
                 local: str = "127.0.0.1", timeout: float = 5.0, idle_timeout: float | None = None) -> None:
        from natnet import NatNetClient

        if units not in MM_PER_UNIT:
            raise ValueError(f"NatNet units {units!r}: expected one of {sorted(MM_PER_UNIT)}")
        self.scale = MM_PER_UNIT[units]
        self.unlabelled = unlabelled or labels is None
        self.labels = None if self.unlabelled else list(labels)
        self.marker_set = marker_set
        self._start_queue(f"natnet {server}:{port}", idle_timeout)
        self._descriptions = None
        self.client = NatNetClient(server_ip_address=server, local_ip_address=local, command_port=port,
                                   use_multicast=False)
        self.client.on_data_frame_received_event.handlers.append(self._hand_over)
        self.client.on_data_description_received_event.handlers.append(self._on_descriptions)
        try:
            self.client.connect(timeout)
        except (TimeoutError, OSError) as exc:
            raise NatNetSourceError(f"NatNet server {server}:{port}: no answer ({type(exc).__name__})") from None
        self._socket = self.client._NatNetClient__command_socket  # unicast: frames arrive here
        self._names: list[str] = []
        if not self.unlabelled:
            self._await_descriptions(server, port, timeout)
        self._thread = threading.Thread(target=self._receive, daemon=True)
        self._thread.start()

    def _await_descriptions(self, server: str, port: int, timeout: float) -> None:
        self.client.request_modeldef()
        deadline = time.monotonic() + timeout
        while self._descriptions is None and time.monotonic() < deadline:
            self._pump(0.1)
        if self._descriptions is None:
            raise NatNetSourceError(f"NatNet server {server}:{port}: no data descriptions")
        for ms in self._descriptions.marker_sets:
            if (self.marker_set is None and set(ms.marker_names) & set(self.labels)) or ms.name == self.marker_set:
                self.marker_set, self._names = ms.name, list(ms.marker_names)
                break
        else:
            raise NatNetSourceError(f"NatNet server {server}:{port}: no marker set "
                                    f"{self.marker_set or 'holding the session labels'}")
        where = {lab: i for i, lab in enumerate(self._names)}
        self._map = np.array([where.get(lab, -1) for lab in self.labels])

    # ------------------------------------------------------------------ receiving
    def _pump(self, wait: float) -> None:
        if not select.select([self._socket], [], [], wait)[0]:
            return
        try:
            self.client.update_sync()
        except (struct.error, ValueError, UnicodeDecodeError, IndexError, AssertionError) as exc:
            self.bad.skip("malformed", f"unreadable NatNet packet ({type(exc).__name__}: {exc})")
        except Exception as exc:  # the package's own protocol errors
            self.bad.skip("malformed", f"unreadable NatNet packet ({type(exc).__name__}: {exc})")

    def _receive(self) -> None:
        while self._running:
            try:
                self._pump(0.2)
            except OSError:  # socket closed under us: the session is over
                break
        self._queue.put(None)

    def _on_descriptions(self, descriptions) -> None:
        self._descriptions = descriptions

    def decode(self, frame) -> MarkerFrame | None:
        number = frame.prefix.frame_number
        order = self._order.check(number)
        if order:
            self.bad.skip(order, f"frame {number} after {self._order.last}")
            return None
        ts = float(frame.suffix.timestamp)
        if self.unlabelled:
            pts = [m.pos for m in frame.labeled_markers or () if not (m.param or 0) & 0x01]
            if not pts:
                pts = list(frame.unlabeled_marker_pos or ())
            p = np.array(pts, dtype=np.float64).reshape(-1, 3) * self.scale
            valid = np.isfinite(p).all(1)
            return MarkerFrame(number, ts, np.where(valid[:, None], p, 0.0), valid)
        ms = next((m for m in frame.marker_sets if m.model_name == self.marker_set), None)
        if ms is None or len(ms.marker_pos_list) != len(self._names):
            self.bad.skip("malformed", f"frame {number}: marker set {self.marker_set} missing or resized")
            return None
        p = np.array(ms.marker_pos_list, dtype=np.float64).reshape(-1, 3) * self.scale
        ok_src = np.isfinite(p).all(1) & (np.abs(p).sum(1) > 0)  # Motive sends an occluded marker as 0,0,0
        has = self._map >= 0
        pos = np.zeros((len(self.labels), 3))
        ok = np.zeros(len(self.labels), dtype=bool)
        pos[has] = p[self._map[has]]
        ok[has] = ok_src[self._map[has]]
        return MarkerFrame(number, ts, np.where(ok[:, None], pos, 0.0), ok)

    # ------------------------------------------------------------------ consumer
    def close(self) -> None:
        self._running = False
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        self.client.shutdown()
