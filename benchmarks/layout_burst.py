"""A layout-eviction attacker (issue 36.1): once per second, a burst of well-formed marker packets,
each announcing a fresh layout under its true id, sent to a driver's bound ZeroMQ SUB socket.
Used by tests/test_layout_eviction.py and benchmarks/hostile.py.

    python -m benchmarks.layout_burst ADDRESS [--burst 20] [--markers 60] [--seconds 10]

Connects a PUB to ADDRESS (``livecap run --zmq-in ADDRESS --zmq-in-bind``) beside an honest sender.
Each burst is more packets than the receiver's layout table holds, so on a table that learns
whatever arrives the honest stream's layout is evicted every second. Prints a JSON line with what
it sent.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import zmq

from transport.wire import encode_markers, layout_id, topic


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("address")
    ap.add_argument("--burst", type=int, default=20, help="packets per burst, one burst a second")
    ap.add_argument("--markers", type=int, default=60, help="markers per packet (fresh names)")
    ap.add_argument("--seconds", type=float, default=10.0)
    args = ap.parse_args(argv)
    n = args.markers
    sock = zmq.Context.instance().socket(zmq.PUB)
    sock.setsockopt(zmq.LINGER, 2000)
    sock.connect(args.address)
    print("ready", flush=True)
    tp = topic("markers", "actor")
    sent = {"packets": 0, "bytes": 0}
    pos, val = np.zeros((n, 3)), np.ones(n, bool)
    t0 = time.perf_counter()
    burst = 0
    while time.perf_counter() - t0 < args.seconds:
        for _ in range(args.burst):
            k = sent["packets"]
            labels = [f"burst{k}_{j}" for j in range(n)]
            payload = encode_markers(0, 0.0, pos, val, labels, layout_id(labels))
            sock.send_multipart([tp, payload])
            sent["packets"] += 1
            sent["bytes"] += len(payload)
        burst += 1
        time.sleep(max(0.0, t0 + burst - time.perf_counter()))
    sent["seconds"] = time.perf_counter() - t0
    sock.close()
    print(json.dumps(sent), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
