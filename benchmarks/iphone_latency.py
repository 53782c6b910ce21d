"""iPhone latency: a Live Link Face packet sent -> the weights received, against a bare UDP relay.

The 180 real app packets (../shared/realdata/performance/dao.gesichter), looped, each with its frame
number rewritten to its index, are sent at ``--rate`` (the app's 60 Hz) from this process over
loopback UDP, through a bare relay process (recv -> sendto, nothing decoded), a *floor* relay (recv, livecap's
decode with every check, the Live Link sink's encode, sendto: the least a Python relay of these packets does) or
``livecap run --livelink-in ... --livelink ... --timecode take`` (decode, every step of a live
session, encode), and received back here; latency = receive time - send time of the same frame.
Both paths run in the same invocation, alternately, ``--runs`` times; the tables hold the medians
over runs of each p99 and of each run's p99 / that run's bare p99 (issue 40 asks <= 1.5). With
``--baseline DIR`` a third path runs ``livecap run`` from another checkout (e.g. /work/main) in the same
runs, so a change is measured against what it replaces on the same load. ``--driver`` adds flags to
livecap's command line (comma-separated), e.g. ``--driver=--rig,DIR,--transfer`` for a retargeted path.

    python -m benchmarks.iphone_latency [--quick] [--runs 3] [--baseline /work/main] [--driver=FLAGS]
"""

from __future__ import annotations

import gzip
import os
import re
import socket
import struct
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np

from benchmarks.processes import first_line, spawn
from benchmarks.timing import suite_main
from tests.conftest import SHARED
from transport.livelink_source import decode_livelink

PACKETS = SHARED / "realdata" / "performance" / "dao.gesichter"

RELAY = """
import socket, sys
rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
rx.bind(("127.0.0.1", 0))
tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
out = ("127.0.0.1", int(sys.argv[1]))
rx.settimeout(3.0)
print(f"relay 127.0.0.1:{rx.getsockname()[1]}", flush=True)
while True:
    try:
        tx.sendto(rx.recv(65536), out)
    except TimeoutError:
        break
"""

FLOOR = """
import socket, sys
from transport.livelink import _body, livelink_header
from transport.livelink_source import decode_livelink
rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
rx.bind(("127.0.0.1", 0))
tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
out = ("127.0.0.1", int(sys.argv[1]))
header = livelink_header("livecap")
rx.settimeout(3.0)
print(f"relay 127.0.0.1:{rx.getsockname()[1]}", flush=True)
while True:
    try:
        p = decode_livelink(rx.recv(65536))
    except TimeoutError:
        break
    tx.sendto(header + _body(list(p.floats), p.frame, p.sub_frame, p.fps, p.denominator), out)
"""


def real_packets() -> list[bytes]:
    """The LLV recording: gzip of u8 version, u32 count, then count x (u32 size, packet); big-endian.
    A ValueError unless its packets account for every byte (tests/test_iphone.py reads it here too)."""
    data = gzip.open(PACKETS).read()
    (count,) = struct.unpack_from(">I", data, 1)
    out, i = [], 5
    for _ in range(count):
        (size,) = struct.unpack_from(">I", data, i)
        out.append(data[i + 4:i + 4 + size])
        i += 4 + size
    if i != len(data):
        raise ValueError(f"{PACKETS}: {count} packets end at byte {i}, the file has {len(data)}")
    return out


def _with_frame(pkt: bytes, frame: int) -> bytes:
    (n_id,) = struct.unpack_from(">i", pkt, 1)
    (n_name,) = struct.unpack_from(">i", pkt, 5 + n_id)
    at = 9 + n_id + n_name
    return pkt[:at] + struct.pack(">if", frame, 0.0) + pkt[at + 8:]


def _measure(proc_args: list, address_pattern: str, count: int, rate: float, tree: str = "") -> tuple[dict, str]:
    """Start the path's process (from checkout ``tree``, default this one) with our receive port, send ``count``
    packets, time each one back."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    args = [a.replace("{RX}", str(rx.getsockname()[1])) for a in map(str, proc_args)]
    proc = spawn(args) if not tree else subprocess.Popen(
        [sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tree,
        env={**os.environ, "PYTHONPATH": tree})
    port = int(re.search(address_pattern, first_line(proc)).group(1))
    pkts = real_packets()
    sent_at = np.full(count, np.nan)
    got_at = np.full(count, np.nan)

    def receive() -> None:
        while True:
            try:
                d = rx.recv(65536)
            except TimeoutError:
                return
            t = time.perf_counter()
            k = decode_livelink(d).frame
            if 0 <= k < count and np.isnan(got_at[k]):
                got_at[k] = t

    th = threading.Thread(target=receive, daemon=True)
    th.start()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    time.sleep(0.5)
    t0 = time.perf_counter()
    for k in range(count):
        time.sleep(max(0.0, t0 + k / rate - time.perf_counter()))
        d = _with_frame(pkts[k % len(pkts)], k)
        sent_at[k] = time.perf_counter()
        tx.sendto(d, ("127.0.0.1", port))
    th.join(timeout=30)
    tx.close()
    rx.close()
    out, _ = proc.communicate(timeout=30)
    lat = (got_at - sent_at)[np.isfinite(got_at)] * 1e3
    stats = {"sent": count, "received": int(len(lat))}
    if len(lat):
        stats.update(p50_ms=float(np.percentile(lat, 50)), p99_ms=float(np.percentile(lat, 99)),
                     max_ms=float(lat.max()))
    return stats, out


DRIVER = ["-m", "livecap", "run", "--livelink-in", "127.0.0.1:0", "--livelink", "127.0.0.1:{RX}", "--timecode", "take",
          "--idle-timeout", "2"]


def run(quick: bool = False, runs: tuple = ("",), baseline: tuple = ("",), driver: tuple = ("",),
        rate: float = 60.0) -> dict:
    if not PACKETS.exists():
        print(f"{PACKETS} not present: nothing measured")
        return {}
    n_runs = int(runs[0]) if runs and runs[0] else (1 if quick else 3)
    count = 300 if quick else 1200
    load = os.getloadavg()[0]
    per_run = []
    for _ in range(n_runs):
        bare, _ = _measure(["-c", textwrap.dedent(RELAY), "{RX}"], r"relay [\d.]+:(\d+)", count, rate)
        floor, _ = _measure(["-c", textwrap.dedent(FLOOR), "{RX}"], r"relay [\d.]+:(\d+)", count, rate)
        floor["p99_over_bare"] = floor.get("p99_ms", float("nan")) / bare.get("p99_ms", float("nan"))
        row = {"bare_udp": bare, "floor": floor}
        for path, tree in [("livecap", ""), ("baseline", baseline[0])] if baseline[0] else [("livecap", "")]:
            drv, _ = _measure(DRIVER + [a for a in driver if a], r"livelink-in [\d.]+:(\d+)", count, rate, tree)
            drv["p99_over_bare"] = drv.get("p99_ms", float("nan")) / bare.get("p99_ms", float("nan"))
            row[path] = drv
        per_run.append(row)

    def med(path: str, key: str) -> float:
        return float(np.median([r[path].get(key, np.nan) for r in per_run]))

    out = {"rate_hz": rate, "packets": count, "runs": n_runs, "per_run": per_run,
           "bare_udp": {k: med("bare_udp", k) for k in ("received", "p50_ms", "p99_ms", "max_ms")},
           **{path: {k: med(path, k) for k in ("received", "p50_ms", "p99_ms", "max_ms", "p99_over_bare")}
              for path in per_run[0] if path != "bare_udp"},
           "machine": f"{os.cpu_count()} CPUs, load average {load:.2f} at start, {os.getloadavg()[0]:.2f} at the end",
           "data": "dao.gesichter: 180 real Live Link Face packets (v6, 60 fps), looped, frame = index",
           "baseline_tree": baseline[0], "driver_flags": [a for a in driver if a]}
    print(f"iPhone latency, Live Link Face packet sent -> Live Link packet received, {count} packets at "
          f"{rate:g} Hz, medians over {n_runs} run(s) ({out['machine']})")
    print(f"{'path':10s} {'recv/sent':>10s} {'p50 ms':>8s} {'p99 ms':>8s} {'max ms':>8s} {'p99/bare':>9s}")
    for path in per_run[0]:
        r = out[path]
        print(f"{path:10s} {r['received']:>5.0f}/{count:<4d} {r['p50_ms']:8.3f} {r['p99_ms']:8.3f} {r['max_ms']:8.3f} "
              f"{r.get('p99_over_bare', 1.0):9.2f}")
    return out


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__, runs="", baseline="", driver=""))
