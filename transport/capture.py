"""``livecap run --qtm-in`` / ``--natnet-in``: the capture-system source for HOST[:PORT]."""

from __future__ import annotations

import queue
import time
from collections.abc import Callable, Iterator

from livecap.core.take import MarkerFrame


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


def _host_port(text: str, default: int) -> tuple[str, int]:
    host, _, port = text.rpartition(":") if ":" in text else (text, "", "")
    try:
        return host or "127.0.0.1", int(port) if port else default
    except ValueError:
        raise ValueError(f"{text!r}: expected HOST[:PORT]") from None


def capture_source(qtm: str | None, natnet: str | None, labels: list[str], unlabelled: bool,
                   idle_timeout: float | None):
    """The QTM RT or NatNet source and its description for the ``ready`` line."""
    if qtm:
        from transport.qtm import DEFAULT_PORT, QtmSource

        host, port = _host_port(qtm, DEFAULT_PORT)
        return (QtmSource(host, port, labels, unlabelled=unlabelled, idle_timeout=idle_timeout),
                f"qtm-in {host}:{port}")
    from transport.natnet import DEFAULT_PORT, NatNetSource

    host, port = _host_port(natnet, DEFAULT_PORT)
    return (NatNetSource(host, port, labels, unlabelled=unlabelled, idle_timeout=idle_timeout),
            f"natnet-in {host}:{port}")
