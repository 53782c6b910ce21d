"""A hostile sender: real marker frames from a take, interleaved with what a hostile network or a
confused sender delivers (issue 17). Used by tests/test_hostile_cli.py and benchmarks/hostile.py.

    python -m benchmarks.hostile_traffic {zmq,osc} ADDRESS TAKE [--valid N] [--garbage K] [--rate HZ]
        [--poison-at I] [--outlier-at I] [--restart-at I] [--truncate-every J]

ZeroMQ: binds an XPUB on ADDRESS (``tcp://127.0.0.1:PORT``), waits for a subscriber, prints
``ready``. OSC: sends datagrams to ``HOST:PORT``. Valid frames carry the labels on the first
frame and only the layout id after (so a poisoned id would re-order every later frame).
Attacks, each at valid frame I: ``poison`` (labels reversed, sent under the true layout id),
``outlier`` (one extra frame numbered 2**40), ``restart`` (frame numbers and timestamps start
again at 0: a restarted sender), ``truncate`` (OSC: every J-th frame also sent without its last
3 bytes). K garbage messages go between consecutive valid frames. On exit it prints a JSON line
with what it sent.
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import time

import msgpack
import numpy as np

from transport.osc_source import encode_osc_frame
from transport.takefile import read_take
from transport.wire import encode_markers, layout_id, topic

OUTLIER_FRAME = 2**40


def garbage(rng: np.random.Generator, n: int = 64) -> list[bytes]:
    """A fixed pool of malformed payloads, cycled: random bytes, empty, wrong msgpack shapes."""
    pool = [bytes(rng.integers(0, 256, int(rng.integers(1, 200)), dtype=np.uint8)) for _ in range(n - 5)]
    pool += [b"", msgpack.packb([1, 2, 3]), msgpack.packb({"v": 1, "type": "markers"}),
             msgpack.packb({"v": 99, "type": "markers"}), b"#bundle\x00" + bytes(20)]
    return pool


def frames(take_path: str, n: int, rate: float, restart_at: int | None):
    """(frame, timestamp, positions, valid) for ``n`` valid frames, looping the take."""
    take = read_take(take_path)
    for i in range(n):
        k = i if restart_at is None or i < restart_at else i - restart_at
        j = i % take.n_frames
        yield k, k / rate, take.positions[j], take.valid[j]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind", choices=["zmq", "osc"])
    ap.add_argument("address")
    ap.add_argument("take")
    ap.add_argument("--valid", type=int, default=600)
    ap.add_argument("--garbage", type=int, default=0, help="malformed messages between two valid frames")
    ap.add_argument("--rate", type=float, default=240.0, help="valid frames per second (0: as fast as possible)")
    ap.add_argument("--poison-at", type=int)
    ap.add_argument("--outlier-at", type=int)
    ap.add_argument("--restart-at", type=int)
    ap.add_argument("--truncate-every", type=int, default=0)
    ap.add_argument("--layout-flood", type=int, default=0,
                    help="ZeroMQ: this many ~40 KB packets, each announcing a new 3000-label layout under its true id")
    ap.add_argument("--wait", type=float, default=20.0, help="ZeroMQ: seconds to wait for a subscriber")
    args = ap.parse_args(argv)
    labels = read_take(args.take).labels
    lid = layout_id(labels)
    rng = np.random.default_rng(17)
    junk = garbage(rng)
    sent = {"valid": 0, "garbage": 0, "poison": 0, "outlier": 0, "truncated": 0}

    if args.kind == "zmq":
        import zmq

        sock = zmq.Context.instance().socket(zmq.XPUB)
        sock.setsockopt(zmq.SNDHWM, 0)
        sock.bind(args.address)
        print("ready", flush=True)
        if not sock.poll(int(args.wait * 1000)):
            print("no subscriber", file=sys.stderr)
            return 1
        sock.recv()
        time.sleep(0.2)
        tp = topic("markers", "actor")

        def send(payload: bytes) -> None:
            sock.send_multipart([tp, payload])

        def valid(i, f, ts, pos, val) -> None:
            send(encode_markers(f, ts, pos, val, labels if i == 0 else None, lid))

        def poison(f, ts, pos, val) -> None:
            send(encode_markers(f, ts, pos[::-1], val[::-1], labels[::-1], lid))

        def big_layout(k: int) -> None:
            big = [f"L{k}_{j}" for j in range(3000)]
            send(encode_markers(0, 0.0, np.zeros((3000, 3)), np.ones(3000, bool), big, layout_id(big)))
    else:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        host, port = args.address.rsplit(":", 1)
        dest = (host, int(port))
        print("ready", flush=True)

        def send(payload: bytes) -> None:
            sock.sendto(payload, dest)

        def valid(i, f, ts, pos, val) -> None:
            dgram = encode_osc_frame(f, ts, labels, pos, val)
            if args.truncate_every and i % args.truncate_every == 0:
                send(dgram[:-3])
                sent["truncated"] += 1
            send(dgram)

        def poison(f, ts, pos, val) -> None:  # OSC names each marker: reordering cannot be hidden
            send(encode_osc_frame(f, ts, labels, pos, val)[:-3])

    t0 = time.perf_counter()
    g = 0
    for i, (f, ts, pos, val) in enumerate(frames(args.take, args.valid, args.rate, args.restart_at)):
        if args.rate > 0:
            delay = t0 + i / args.rate - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        if i == args.poison_at:
            poison(f, ts, pos, val)
            sent["poison"] += 1
        if i == args.outlier_at:
            valid(i, OUTLIER_FRAME, ts, pos, val)
            sent["outlier"] += 1
        valid(i, f, ts, pos, val)
        sent["valid"] += 1
        if args.kind == "zmq" and sent.setdefault("layouts", 0) < args.layout_flood:
            big_layout(sent["layouts"])
            sent["layouts"] += 1
        for _ in range(args.garbage):
            send(junk[g % len(junk)])
            g += 1
        sent["garbage"] += args.garbage
    sent["seconds"] = time.perf_counter() - t0
    if args.kind == "zmq":
        sock.close(linger=5000)
    print(json.dumps(sent), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
