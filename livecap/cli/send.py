"""``livecap send``: stream a recorded take as live markers over ZeroMQ or OSC, at real-time pace.

A bridge for capture systems that record to files, and the driver the integration tests and
the latency benchmark use. ZeroMQ: binds an XPUB socket and (by default) waits until a
subscriber has joined before the first frame, so nothing is lost to ZeroMQ's slow-joiner
window. OSC: one bundle per frame to HOST:PORT (the receiver must already listen).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def register(sub) -> None:
    p = sub.add_parser("send", help="stream a take (C3D/TRC/CSV) as live markers over ZeroMQ or OSC",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("take", help="marker take: .c3d, .trc, .csv or a raw .npz recording")
    dest = p.add_mutually_exclusive_group(required=True)
    dest.add_argument("--zmq", help="ZeroMQ address to publish markers.<actor> on (binds)")
    dest.add_argument("--osc", help="[HOST:]PORT to send OSC frame bundles to")
    dest.add_argument("--lsl", help="Lab Streaming Layer outlet name (markers, 3 channels per marker, mm)")
    p.add_argument("--strip-labels", action="store_true",
                   help="LSL: no channel labels, markers shuffled every frame (an unlabelled cloud)")
    p.add_argument("--connect", action="store_true", help="ZeroMQ: connect instead of binding")
    p.add_argument("--actor", default="actor", help="actor name in the topic markers.<actor> (default actor)")
    p.add_argument("--speed", type=float, default=1.0, help="pace factor against the take's rate (default 1)")
    p.add_argument("--fast", action="store_true", help="as fast as possible")
    p.add_argument("--loop", action="store_true", help="start again at the end (default: stop)")
    p.add_argument("--start", type=int, help="first frame number")
    p.add_argument("--end", type=int, help="frame number to stop before")
    p.add_argument("--frames", type=int, help="stop after sending this many frames (with --loop: a duration)")
    p.add_argument("--wait-subscriber", type=float, default=10.0,
                   help="ZeroMQ: seconds to wait for a subscriber before sending (0: do not wait)")
    p.add_argument("--labels-every", type=int, default=120,
                   help="ZeroMQ: send the label list every N frames, the layout id in between (0: always)")
    p.add_argument("--clock", choices=["take", "monotonic"], default="take",
                   help="timestamp: the take's time, or this machine's monotonic clock at send (for latency)")
    p.add_argument("--interface", help="allow a non-loopback interface")
    p.add_argument("--curve-secret", help="our secret certificate")
    p.add_argument("--curve-clients", help="folder of allowed client public certificates (when binding)")
    p.add_argument("--curve-server", help="server public certificate (when connecting)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from transport.replay import ReplaySource

    source = ReplaySource.open(args.take, None, speed=args.speed, fast=args.fast, loop=args.loop,
                               start=args.start, end=args.end)
    labels = source.labels
    if args.lsl:
        send = _lsl_sender(args, labels, source.rate)
    else:
        send = _zmq_sender(args, labels) if args.zmq else _osc_sender(args, labels)
    n = 0
    t0 = time.perf_counter()
    try:
        for frame in source:
            ts = time.monotonic() if args.clock == "monotonic" else frame.timestamp
            send(frame.frame, ts, frame.positions, frame.valid, n)
            n += 1
            if args.frames and n >= args.frames:
                break
    except KeyboardInterrupt:
        pass
    finally:
        send(None, 0.0, None, None, n)  # close
    print(f"sent {n} frames of {len(labels)} markers in {time.perf_counter() - t0:.2f} s", flush=True)
    return 0


def _zmq_sender(args, labels):
    import zmq

    from transport.security import curve_from_flags, zmq_address
    from transport.wire import encode_markers, layout_id, topic

    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.XPUB)
    sock.setsockopt(zmq.SNDHWM, 100000)
    curve = curve_from_flags(args.curve_secret, args.curve_clients, args.curve_server)
    if curve is not None:
        curve.apply(sock, server=not args.connect)
    addr = zmq_address(args.zmq, args.interface)
    try:
        if args.connect:
            sock.connect(addr)
        else:
            sock.bind(addr)
            addr = sock.getsockopt(zmq.LAST_ENDPOINT).decode()
    except zmq.ZMQError as exc:  # port in use, an endpoint libzmq refuses: one line via the CLI
        raise ValueError(f"--zmq {addr}: {exc}") from None
    print(f"ready: zmq {addr}", flush=True)
    tp = topic("markers", args.actor)
    if args.wait_subscriber > 0 and sock.poll(int(args.wait_subscriber * 1000), zmq.POLLIN):
        sock.recv()  # a subscription: someone listens
    lid = layout_id(labels)

    def send(frame, ts, positions, valid, n):
        if frame is None:
            sock.close(linger=2000)
            return
        with_labels = args.labels_every <= 0 or n % args.labels_every == 0
        payload = encode_markers(frame, ts, np.asarray(positions), valid, labels if with_labels else None, lid)
        sock.send_multipart([tp, payload])

    return send


def _osc_sender(args, labels):
    import socket

    from transport.osc_source import encode_osc_frame
    from transport.security import udp_address

    host, port = udp_address(args.osc, 9000, args.interface)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    print(f"ready: osc {host}:{port}", flush=True)

    def send(frame, ts, positions, valid, n):
        if frame is None:
            sock.close()
            return
        try:
            sock.sendto(encode_osc_frame(frame, ts, labels, positions, valid), (host, port))
        except OSError:
            pass  # nobody listening yet: UDP is fire-and-forget

    return send


def _lsl_sender(args, labels, rate):
    from transport.lsl import LslMarkerSender, confine

    confine(args.interface)
    out = LslMarkerSender(args.lsl, labels, rate, strip=args.strip_labels)
    print(f"ready: lsl {args.lsl}", flush=True)
    if args.wait_subscriber > 0:
        out.wait_for_consumer(args.wait_subscriber)

    def send(frame, ts, positions, valid, n):
        if frame is None:
            out.close()
            return
        out.send(positions, valid)

    return send
