"""What the capture-system clients (QTM RT, NatNet) share: the vendor client's thread decodes each
packet and hands the frame to the consumer through a bounded queue; a source lost for good says so
(``lost``) so that ``livecap run`` can exit non-zero."""

from __future__ import annotations

import queue
import time
from collections.abc import Callable, Iterator

from livecap.core.take import MarkerFrame
from transport.badinput import BadInput, FrameOrder


def endpoint(host: str, port: int) -> str:
    """``host:port``, or ``[host]:port`` for an IPv6 address (as ``--qtm-in``/``--natnet-in`` take it)."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def offer(frames: queue.Queue, frame: MarkerFrame, bad) -> None:
    """Hand a decoded frame from the client library's thread to the consumer; a full queue is a counted
    ``overrun`` (the consumer is behind), never a blocked network thread."""
    try:
        frames.put_nowait(frame)
    except queue.Full:
        bad.skip("overrun", f"frame {frame.frame}: consumer behind by {frames.qsize()} frames")


def queued_frames(frames: queue.Queue, running: Callable[[], bool],
                  idle_timeout: float | None) -> Iterator[MarkerFrame]:
    """The frames a client library's reader thread puts on ``frames`` (None ends the stream), until the
    source is stopped or nothing has arrived for ``idle_timeout`` seconds."""
    last_good = time.monotonic()
    while running():
        try:
            frame = frames.get(timeout=0.2)
        except queue.Empty:
            if idle_timeout and time.monotonic() - last_good > idle_timeout:
                return
            continue
        if frame is None:
            return
        last_good = time.monotonic()
        yield frame


class QueuedCaptureSource:
    """What the capture-system sources share: the vendor client's thread decodes each packet
    (``decode``, per source) and hands the frame to the consumer through a bounded queue."""

    def _start_queue(self, name: str, idle_timeout: float | None) -> None:
        self.bad = BadInput(name)
        self._order = FrameOrder()
        self.idle_timeout = idle_timeout
        self.received = 0
        self.last_decode_seconds = 0.0
        self._queue: queue.Queue = queue.Queue(maxsize=1000)
        self._running = True
        self.lost: str | None = None  # why the source ended for good, when it was not stopped

    def decode(self, packet) -> MarkerFrame | None:
        raise NotImplementedError

    def _hand_over(self, packet) -> None:
        """The client thread's callback: decode (timed, counted) and offer the frame."""
        t0 = time.perf_counter()
        self.received += 1
        frame = self.decode(packet)
        self.last_decode_seconds = time.perf_counter() - t0
        if frame is not None:
            offer(self._queue, frame, self.bad)

    def pending(self) -> bool:
        return not self._queue.empty()

    def stop(self) -> None:
        self._running = False

    def __iter__(self) -> Iterator[MarkerFrame]:
        return queued_frames(self._queue, lambda: self._running, self.idle_timeout)
