"""iPhone packet cost in-process: what ``livecap run --livelink-in ... --livelink ...`` spends on one packet.

The real source, pipeline loop and Live Link sink, with the two sockets replaced: the source's ``recv``
hands out the 180 real app packets (looped, frame = index) at ``--rate`` and stamps each one's arrival,
the sink's ``sendto`` stamps its departure; cost = departure - arrival. At the app's 60 Hz the process
sleeps between packets as it does live, so the figure includes what a woken process pays for its cold
caches (several times the warm cost, docs/iphone.md, Latency); ``back to back`` is the warm cost. Load
distorts this less than the loopback benchmark (benchmarks/iphone_latency.py): no other process sits
on the path. With ``--baseline DIR`` the same measurement runs on another checkout (e.g. /work/main),
alternately with this one, in the same run. ``decode+encode only`` is the floor for this relay in Python:
the source's decode with all its checks and the sink's packet, none of the session around them.

    python -m benchmarks.iphone_packet_cost [--quick] [--runs 3] [--baseline /work/main]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def measure(count: int, rate: float) -> dict:
    """Arrival -> sendto of ``count`` packets at ``rate`` Hz (0: back to back), µs percentiles."""
    from benchmarks.iphone_latency import _with_frame, real_packets
    from livecap.live.relay import WeightsPipeline
    from transport.livelink import LiveLinkSink
    from transport.livelink_source import LiveLinkFaceSource

    pkts = real_packets()
    data = [_with_frame(pkts[k % len(pkts)], k) for k in range(count)]
    arrived, sent = np.zeros(count), np.zeros(count)

    class Feed:
        """The source's socket: the next packet at its time."""

        k, t0 = 0, 0.0

        def recv(self, size: int) -> bytes:
            if self.k >= count:
                raise OSError("fed every packet")  # the source's "socket closed": the session ends
            if self.k == 0:
                self.t0 = time.perf_counter()
            elif rate:
                time.sleep(max(0.0, self.t0 + self.k / rate - time.perf_counter()))
            arrived[self.k] = time.perf_counter()
            self.k += 1
            return data[self.k - 1]

        def close(self) -> None:
            pass

    class Stamp:
        """The sink's socket: the departure time of each packet."""

        k = 0

        def sendto(self, pkt: bytes, address) -> int:
            sent[self.k] = time.perf_counter()
            self.k += 1
            return len(pkt)

        def close(self) -> None:
            pass

    source = LiveLinkFaceSource("127.0.0.1", 0)
    source.sock.close()
    source.sock = Feed()
    sink = LiveLinkSink("127.0.0.1", 9, timecode="take")
    sink.sock.close()
    sink.sock = Stamp()
    WeightsPipeline(source, [sink], rate=60.0).run()
    us = (sent - arrived)[10:] * 1e6  # the first packets build the sink's name matrix
    p50, p90, p99 = np.percentile(us, [50, 90, 99])
    return {"packets": count, "rate_hz": rate, "p50_us": float(p50), "p90_us": float(p90), "p99_us": float(p99)}


def measure_floor(count: int, rate: float) -> dict:
    """The least a Python relay of these packets does: decode one (every check of the source) and encode a
    Live Link packet of its values (the sink's struct), nothing else; the same timing as :func:`measure`."""
    from benchmarks.iphone_latency import _with_frame, real_packets
    from transport.livelink import _body, livelink_header
    from transport.livelink_source import decode_livelink

    pkts = real_packets()
    data = [_with_frame(pkts[k % len(pkts)], k) for k in range(count)]
    header = livelink_header("livecap")
    us = np.zeros(count)
    t0 = time.perf_counter()
    for k in range(count):
        if rate:
            time.sleep(max(0.0, t0 + k / rate - time.perf_counter()))
        t = time.perf_counter()
        p = decode_livelink(data[k])
        header + _body(list(p.floats), p.frame, p.sub_frame, p.fps, p.denominator)
        us[k] = (time.perf_counter() - t) * 1e6
    p50, p90, p99 = np.percentile(us[10:], [50, 90, 99])
    return {"packets": count, "rate_hz": rate, "p50_us": float(p50), "p90_us": float(p90), "p99_us": float(p99)}


def _child(tree: str, count: int, rate: float, what: str = "path") -> dict:
    """:func:`measure` (or :func:`measure_floor`) in a fresh process that imports livecap from ``tree``."""
    env = {**os.environ, "PYTHONPATH": tree, "OPENBLAS_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, __file__, "--child", str(count), str(rate), what], cwd=tree, env=env,
                         capture_output=True, text=True, timeout=600)
    if out.returncode:
        raise RuntimeError(f"{tree}: {out.stderr.strip().splitlines()[-1:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def run(quick: bool = False, runs: tuple = ("",), baseline: tuple = ("",)) -> dict:
    from tests.conftest import SHARED

    if not (SHARED / "realdata" / "performance" / "dao.gesichter").exists():
        print("../shared/realdata/performance/dao.gesichter not present: nothing measured")
        return {}
    n_runs = int(runs[0]) if runs and runs[0] else (1 if quick else 3)
    count = 300 if quick else 600
    trees = {"livecap": str(ROOT), **({"baseline": baseline[0]} if baseline[0] else {})}
    load = os.getloadavg()[0]
    per_run = []
    for _ in range(n_runs):
        row = {f"{name} {label}": _child(tree, n, rate) for name, tree in trees.items()
               for label, n, rate in (("60 Hz", count, 60.0), ("back to back", 2000, 0.0))}
        row["decode+encode only 60 Hz"] = _child(str(ROOT), count, 60.0, "floor")
        per_run.append(row)
    rows = {key: {k: float(np.median([r[key][k] for r in per_run])) for k in ("p50_us", "p90_us", "p99_us")}
            for key in per_run[0]}
    out = {"runs": n_runs, "per_run": per_run, "median": rows, "baseline_tree": baseline[0],
           "machine": f"{os.cpu_count()} CPUs, load average {load:.2f} at start, {os.getloadavg()[0]:.2f} at the end",
           "data": "dao.gesichter: 180 real Live Link Face packets (v6), looped"}
    print(f"iPhone packet cost in-process (recv returned -> sendto called), medians over {n_runs} run(s), "
          f"{out['machine']}")
    print(f"{'path':28s} {'p50 us':>8s} {'p90 us':>8s} {'p99 us':>8s}")
    for key, r in rows.items():
        print(f"{key:28s} {r['p50_us']:8.1f} {r['p90_us']:8.1f} {r['p99_us']:8.1f}")
    return out


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        del sys.path[0]  # this file's folder: livecap and benchmarks come from the tree on PYTHONPATH
        what = measure_floor if sys.argv[4:5] == ["floor"] else measure
        print(json.dumps(what(int(sys.argv[2]), float(sys.argv[3]))))
        sys.exit(0)
    from benchmarks.timing import suite_main

    sys.exit(suite_main(run, __doc__, runs="", baseline=""))
