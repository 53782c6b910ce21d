"""ZeroMQ publisher of weights: ``[b"weights.<actor>", msgpack payload]`` per frame.

An XPUB socket, so the sink sees each subscriber join and re-sends the shape-name header to
it at once (and every ``header_every`` seconds for anyone who missed it). Sends never block
the solver:

* ``policy="fair"`` (default): plain PUB semantics; libzmq drops frames only for the slow
  subscriber, silently (nothing to count), and the others keep receiving every frame. The
  default because one dead or slow client must never cost another anything (issue 17).
* ``policy="count"``: XPUB_NODROP + non-blocking sends. When a subscriber's queue (send
  high-water mark) is full the frame is not sent and :attr:`drops` counts it. Caveat of
  ZeroMQ's fan-out: while one subscriber is stuck, every subscriber misses those frames.
"""

from __future__ import annotations

import time

import zmq

from transport.security import Curve
from transport.wire import encode_header, encode_weights, layout_id, topic


class ZmqSink:
    def __init__(self, address: str, actor: str = "actor", hwm: int = 100, policy: str = "fair",
                 header_every: float = 1.0, curve: Curve | None = None, bind: bool = True,
                 rate: float | None = None, sndbuf: int | None = None, context: zmq.Context | None = None) -> None:
        if policy not in ("count", "fair"):
            raise ValueError(f"unknown ZeroMQ drop policy {policy!r} (count or fair)")
        self.actor = actor
        self.topic = topic("weights", actor)
        self.header_every = header_every
        self.rate = rate
        self.policy = policy
        self.sent = 0
        self.drops = 0
        self.header_drops = 0
        self.joins = 0
        self._names: list[str] | None = None
        self._names_ref: object = None
        self._names_id = ""
        self._header = b""
        self._last_header = -1e9
        self._ctx = context or zmq.Context.instance()
        self.sock = self._ctx.socket(zmq.XPUB)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.SNDHWM, hwm)
        if sndbuf:
            self.sock.setsockopt(zmq.SNDBUF, sndbuf)
        self.sock.setsockopt(zmq.XPUB_VERBOSE, 1)
        if policy == "count":
            self.sock.setsockopt(zmq.XPUB_NODROP, 1)
        if curve is not None:
            curve.apply(self.sock, server=bind)
        if bind:
            self.sock.bind(address)
            self.address = self.sock.getsockopt(zmq.LAST_ENDPOINT).decode()
        else:
            self.sock.connect(address)
            self.address = address

    def _send(self, payload: bytes) -> bool:
        try:
            self.sock.send_multipart([self.topic, payload], flags=zmq.NOBLOCK)
            return True
        except zmq.Again:
            return False

    def _joined(self) -> bool:
        """Drain subscription notices; True when someone (re)subscribed to our topic."""
        joined = False
        while self.sock.getsockopt(zmq.EVENTS) & zmq.POLLIN:  # no exception raised per frame
            try:
                msg = self.sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                return joined
            if msg[:1] == b"\x01" and self.topic.startswith(msg[1:]):
                joined = True
                self.joins += 1
        return joined

    def publish(self, result) -> None:
        if result.names is not self._names_ref:  # names are shared per session: compare rarely
            if self._names is None or list(result.names) != self._names:
                self._names_id = layout_id(result.names)
                self._header = encode_header(result.names, self.actor, self.rate)
                self._last_header = -1e9
            self._names, self._names_ref = list(result.names), result.names
        now = time.monotonic()
        if self._joined() or now - self._last_header >= self.header_every:
            if self._send(self._header):
                self._last_header = now
            else:
                self.header_drops += 1
        if self._send(encode_weights(result, self._names_id)):
            self.sent += 1
        else:
            self.drops += 1

    def stats(self) -> dict:
        return {"sent": self.sent, "drops": self.drops, "header_drops": self.header_drops, "joins": self.joins}

    def close(self) -> None:
        self.sock.close(0)
