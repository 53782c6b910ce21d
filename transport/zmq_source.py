"""ZeroMQ SUB source: ``[b"markers.<actor>", msgpack payload]`` in, MarkerFrames out.

Connects (default) or binds a SUB socket, subscribes to ``markers.<actor>`` and decodes each
message with :func:`transport.wire.decode_markers`. Bad packets and out-of-order frames are
counted in :attr:`bad` and skipped; the iterator only ends on :meth:`stop` or after
``idle_timeout`` seconds without a good frame.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import zmq

from livecap.core.take import MarkerFrame
from transport.badinput import BadInput, FrameOrder, LabelMap
from transport.security import Curve
from transport.wire import MAX_MESSAGE_BYTES, LayoutTable, WireError, decode_markers, topic

DRAIN = 1000  # messages decoded per look before the loop checks stop and idle time


class ZmqSource:
    def __init__(self, address: str, labels: list[str], actor: str = "actor", bind: bool = False,
                 curve: Curve | None = None, idle_timeout: float | None = None,
                 first_frame_timeout: float | None = None, poll_ms: int = 100,
                 context: zmq.Context | None = None) -> None:
        self.address = address
        self.labels = list(labels)
        self.topic = topic("markers", actor)
        self.bad = BadInput(f"zmq {address}")
        self.idle_timeout = idle_timeout
        # senders usually start after the driver: waiting for the first frame gets its own limit
        self.first_frame_timeout = first_frame_timeout
        self.poll_ms = poll_ms
        self.last_decode_seconds = 0.0
        self.received = 0
        self._map = LabelMap(self.labels)
        self._order = FrameOrder()
        self._layouts = LayoutTable(allowed=self.labels)
        self._layouts.pin(self.labels)
        self._running = True
        self._ahead: MarkerFrame | None = None
        self._seen_good = False
        self._ctx = context or zmq.Context.instance()
        self.sock = self._ctx.socket(zmq.SUB)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.RCVHWM, 10000)
        self.sock.setsockopt(zmq.MAXMSGSIZE, MAX_MESSAGE_BYTES + 4096)  # libzmq drops the peer that sends more
        if curve is not None:
            curve.apply(self.sock, server=bind)
        self.sock.setsockopt(zmq.SUBSCRIBE, self.topic)
        if bind:
            self.sock.bind(address)
        else:
            self.sock.connect(address)

    def pending(self) -> bool:
        """True when another *valid* frame is already waiting (the pipeline then skips a stale
        frame). Garbage in the queue is decoded and counted here, so it never makes a real frame
        look stale."""
        if self._ahead is None:
            self._ahead = self._next()
        return self._ahead is not None

    def _next(self) -> MarkerFrame | None:
        """The next good frame already received, or None (after at most ``DRAIN`` messages)."""
        t0 = time.perf_counter()
        if not self.sock.getsockopt(zmq.EVENTS) & zmq.POLLIN:  # the usual empty queue, without raising zmq.Again
            return None
        for _ in range(DRAIN):
            try:
                parts = self.sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return None
            self.received += 1
            frame = self.decode(parts)
            if frame is not None:
                self.last_decode_seconds = time.perf_counter() - t0
                return frame
        return None

    def stop(self) -> None:
        self._running = False

    def close(self) -> None:
        self._running = False
        self.sock.close(0)

    def decode(self, parts: list[bytes]) -> MarkerFrame | None:
        """One message to a frame in the session's label order, or None (counted) when bad."""
        if len(parts) != 2:
            self.bad.skip("malformed", f"{len(parts)}-part message, expected [topic, payload]")
            return None
        if parts[0] != self.topic:
            return None  # a longer topic that shares our prefix: not for us
        try:
            pkt = decode_markers(parts[1], self._layouts)
            if pkt.labels == self.labels:  # the session's order (the usual case): the decoded arrays as they are
                frame = MarkerFrame(pkt.frame, pkt.timestamp, pkt.positions, pkt.valid)
            else:
                frame = self._map.frame(pkt.frame, pkt.timestamp, pkt.labels, pkt.positions, pkt.valid)
        except WireError as exc:
            self.bad.skip(exc.kind, str(exc))
            if exc.kind == "unknown_label":
                self.bad.check_labels_match(self._seen_good, str(exc))
            return None
        except KeyError as exc:
            self.bad.skip("unknown_label", str(exc.args[0]))
            self.bad.check_labels_match(self._seen_good, str(exc.args[0]))
            return None
        if not self.bad.in_order(self._order, frame.frame, frame.timestamp):
            return None
        if pkt.layout is not None:
            self._layouts.active = pkt.layout  # the honest stream's layout, in whatever label order it sends
        self._seen_good = True
        return frame

    def __iter__(self) -> Iterator[MarkerFrame]:
        last_good = time.monotonic()  # no frame at all ends the session after first_frame_timeout
        limit = self.first_frame_timeout if self.first_frame_timeout is not None else self.idle_timeout
        poller = zmq.Poller()
        poller.register(self.sock, zmq.POLLIN)
        while self._running:
            frame, self._ahead = self._ahead, None
            if frame is None:
                frame = self._next()
            if frame is not None:
                last_good = time.monotonic()
                limit = self.idle_timeout
                yield frame
                if self._ahead is None and self._running:  # wait here: the queue is usually empty after a frame
                    poller.poll(self.poll_ms)
                continue
            if limit and time.monotonic() - last_good > limit:
                return  # checked outside the poll: a flood of garbage does not keep a dead session alive
            poller.poll(self.poll_ms)
