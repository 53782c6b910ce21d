"""Concurrency: how many actor streams at 120 Hz the drivers sustain on this machine.

Real processes and real ZeroMQ on 127.0.0.1, as in a session with several actors:

* one **sender** process publishes N actors' marker streams (``markers.a0`` ... ``markers.a<N-1>``,
  the demo take looped, payloads as ``livecap send`` makes them) at 120 Hz, each packet stamped
  with the machine's monotonic clock when it is sent;
* the **drivers** solve them, in one of three layouts:
  - ``1 process``: all N pipelines in threads of one process (benchmarks/multi_driver.py: each
    pipeline built by ``livecap run``'s own option parser and ``build``; ``livecap run`` itself
    serves one actor per process, so this is the only way one process serves N);
  - ``2 processes`` (one per core): the same, the actors split between two processes;
  - ``process per actor``: N ``livecap run --actor aK`` processes;
* one **receiver** process subscribes to every ``weights.<actor>`` stream and records, for each
  weights message, ``now - timestamp``.

The drivers run with ``--no-skip-stale`` (every frame is solved; a driver that cannot keep up
shows as growing latency). A layout *sustains* N actors when, over a run of ``seconds``: every
frame of every actor reaches the receiver (none dropped by a sink or a socket), and the
99th percentile of the send -> receive latency over all actors' frames (the first 0.5 s of each
stream excluded as warm-up) is below one frame period (8.33 ms). N is searched upward (1, 2, 4,
8, 12, 16, 24, 32); the search stops at the first N that fails twice in a row (one retry,
because the machine is shared and a burst of someone else's work can fail a run). The sender
and receiver run on the same 2 cores as the drivers and take their share of CPU.

    python -m benchmarks.concurrency [--quick] [--modes qp,movement-stream] [--layouts 1,2,per-actor]
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

from benchmarks.processes import first_line, free_port, spawn
from benchmarks.timing import suite_main

RATE = 120.0
LEVELS = (1, 2, 4, 8, 12, 16, 24, 32)
WARMUP_S = 0.5

SENDER = """
import json, sys, time, zmq
from livecap.calibration.profile import Profile
from transport.takefile import read_take
from transport.wire import encode_markers, layout_id, topic
take_path, profile_path, port, n, seconds, rate = sys.argv[1:7]
n, seconds, rate = int(n), float(seconds), float(rate)
labels = Profile.load(profile_path).labels
take = read_take(take_path).select(labels)
sock = zmq.Context().socket(zmq.XPUB)
sock.setsockopt(zmq.SNDHWM, 1000000)
sock.bind(f"tcp://127.0.0.1:{port}")
topics = [topic("markers", f"a{i}") for i in range(n)]
print("ready", flush=True)
seen, deadline = set(), time.monotonic() + 120
while not set(topics) <= seen and time.monotonic() < deadline:
    if sock.poll(500):
        msg = sock.recv()
        if msg[:1] == b"\\x01":
            seen.add(msg[1:])
if not set(topics) <= seen:
    sys.exit(f"only {len(seen)} of {n} drivers subscribed")
time.sleep(0.3)
lid, frames, late = layout_id(labels), int(seconds * rate), 0
t0 = time.monotonic()
for k in range(frames):
    due = t0 + k / rate
    wait = due - time.monotonic()
    if wait > 0:
        time.sleep(wait)
    elif wait < -1 / rate:
        late += 1
    i = k % take.n_frames
    for tp in topics:
        payload = encode_markers(k, time.monotonic(), take.positions[i], take.valid[i],
                                 labels if k % 120 == 0 else None, lid)
        sock.send_multipart([tp, payload])
print(json.dumps({"sent": frames, "late_ticks": late, "seconds": time.monotonic() - t0}), flush=True)
sock.close(linger=5000)
"""

RECEIVER = """
import json, sys, time, msgpack, zmq
out, idle, addrs = sys.argv[1], float(sys.argv[2]), sys.argv[3:]
s = zmq.Context().socket(zmq.SUB)
s.setsockopt(zmq.RCVHWM, 1000000)
for a in addrs:
    s.connect(a)
s.setsockopt(zmq.SUBSCRIBE, b"weights.")
time.sleep(1.0)
print("ready", flush=True)
got, last, start = {}, None, time.monotonic()
while True:
    if not s.poll(int(idle * 1000)):
        if last is not None or time.monotonic() - start > 600:
            break
        continue
    topic, payload = s.recv_multipart()
    now = time.monotonic()
    last = now
    msg = msgpack.unpackb(payload)
    if msg.get("type") == "weights":
        got.setdefault(topic.decode()[8:], []).append((msg["frame"], now - msg["timestamp"]))
json.dump(got, open(out, "w"))
"""










def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a running process so far (from /proc/<pid>/stat)."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _drivers(layout: str, n: int, port: int, profile: Path, mode: str, stats: Path) -> list[subprocess.Popen]:
    # --no-skip-stale: every frame is solved, so a driver that cannot keep up shows as latency
    # growing past the frame period rather than as skipped frames
    common = ["--zmq-in", f"tcp://127.0.0.1:{port}", "--profile", profile, "--mode", mode, "--idle-timeout", 2.0,
              "--no-skip-stale"]
    actors = [f"a{i}" for i in range(n)]
    if layout == "per-actor":
        return [spawn(["-m", "livecap", "run", *common, "--actor", a, "--zmq-out", "tcp://127.0.0.1:0",
                        "--stats-file", stats / f"{a}.json"]) for a in actors]
    k = min(int(layout), n)
    groups = [actors[i::k] for i in range(k)]
    return [spawn(["-m", "benchmarks.multi_driver", "--actors", *g, "--stats-dir", stats, "--", *common])
            for g in groups]


def trial(layout: str, n: int, mode: str, seconds: float, take: Path, profile: Path, work: Path) -> dict:
    """One run: N actors for ``seconds``; returns the counts, latency percentiles and the verdict."""
    stats = work / f"stats-{layout}-{mode}-{n}-{time.monotonic_ns()}"
    stats.mkdir()
    port = free_port()
    drivers = _drivers(layout, n, port, profile, mode, stats)
    outs = []
    try:
        for d in drivers:
            ready = first_line(d)
            outs += re.findall(r"tcp://[\d.]+:\d+", ready.split("zmq-out", 1)[-1] if "zmq-out" in ready else ready)
        rx = spawn(["-c", textwrap.dedent(RECEIVER), stats / "rx.json", 3.0, *outs])
        first_line(rx)
        sender = spawn(["-c", textwrap.dedent(SENDER), take, profile, port, n, seconds, RATE])
        first_line(sender)
        t0 = time.monotonic()
        cpu0 = sum(_cpu_seconds(d.pid) for d in drivers)  # start-up (imports, solver set-up) excluded
        s_out, s_err = sender.communicate(timeout=seconds + 180)
        if sender.returncode:
            raise RuntimeError(f"sender failed: {s_err[-500:]}")
        sent = json.loads(s_out.strip().splitlines()[-1])
        cpu = -cpu0
        for d in drivers:
            _, status, usage = os.wait4(d.pid, 0)
            d.returncode = os.waitstatus_to_exitcode(status)
            d.communicate()
            cpu += usage.ru_utime + usage.ru_stime
        wall = time.monotonic() - t0
        rx.communicate(timeout=120)
    finally:
        for p in drivers:
            if p.poll() is None:
                p.kill()
                p.communicate()
    got = json.loads((stats / "rx.json").read_text())
    per_actor = {a: got.get(a, []) for a in (f"a{i}" for i in range(n))}
    received = {a: len({f for f, _ in v}) for a, v in per_actor.items()}
    warm = int(WARMUP_S * RATE)
    lat = np.array([x for v in per_actor.values() for f, x in v if f >= warm]) * 1e3
    driver_stats = [json.loads((stats / f"a{i}.json").read_text()) for i in range(n)]
    stale = sum(s.get("stale", 0) for s in driver_stats)
    drops = sum(v.get("drops", 0) for s in driver_stats for v in s["sinks"].values())
    p50, p99 = (np.percentile(lat, [50, 99]) if len(lat) else (float("nan"), float("nan")))
    every = all(r == sent["sent"] for r in received.values())
    return {"layout": layout, "actors": n, "mode": mode, "seconds": seconds, "sent_per_actor": sent["sent"],
            "received_min": min(received.values()), "received_total": sum(received.values()), "stale": stale,
            "sink_drops": drops, "sender_late_ticks": sent["late_ticks"], "p50_ms": float(p50), "p99_ms": float(p99),
            "max_ms": float(lat.max()) if len(lat) else float("nan"),
            "driver_cpu_pct": 100 * cpu / seconds, "wall_s": wall,  # CPU per second of stream (of 200% on 2 cores)
            "load": os.getloadavg()[0],
            "sustained": bool(every and p99 < 1e3 / RATE)}


def search(layout: str, mode: str, seconds: float, take: Path, profile: Path, work: Path,
           levels=LEVELS) -> dict:
    """Largest N in ``levels`` sustained (searching upward; a failed level is retried once)."""
    trials, best = [], 0
    for n in levels:
        ok = False
        for _attempt in range(2):
            r = trial(layout, n, mode, seconds, take, profile, work)
            trials.append(r)
            print(f"  {mode:16s} {_layout_name(layout):17s} N={n:<3d} {'ok  ' if r['sustained'] else 'FAIL'} "
                  f"received {r['received_min']}/{r['sent_per_actor']} (min over actors), stale {r['stale']}, "
                  f"p50 {r['p50_ms']:.2f} ms, p99 {r['p99_ms']:.2f} ms, driver CPU {r['driver_cpu_pct']:.0f}%, "
                  f"load {r['load']:.1f}", flush=True)
            if r["sustained"]:
                ok = True
                break
        if not ok:
            break
        best = n
    return {"layout": layout, "mode": mode, "sustained_actors": best, "trials": trials}


def _layout_name(layout: str) -> str:
    return {"1": "1 process", "2": "2 processes", "per-actor": "process per actor"}[layout]


def run(quick: bool = False, modes=("qp", "movement-stream"), layouts=("1", "2", "per-actor")) -> dict:
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.demo import DEMO_TAKE, generate
    from livecap.demo.performance import PerformanceSettings
    from transport.takefile import read_take

    seconds = 5.0 if quick else 20.0
    load = os.getloadavg()[0]
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        generate(work, 0, PerformanceSettings(seconds=10, rate=RATE, seed=1))
        rig = Rig.load(work / "demo_rig.npz")
        layout_ = MarkerLayout.load(work / "demo_rig.markers.json", rig)
        take = read_take(work / DEMO_TAKE).select(layout_.labels)
        calibrate(rig, layout_, estimate_neutral(take, layout_.stable, 120)).save(work / "profile.npz")
        print(f"concurrency at {RATE:g} Hz, {seconds:g} s per trial (load average {load:.2f}); sustained = every "
              f"frame received and p99 < {1e3 / RATE:.2f} ms", flush=True)
        for mode in modes:
            for lay in layouts:
                results.append(search(lay, mode, seconds, work / DEMO_TAKE, work / "profile.npz", work))
    out = {"rate_hz": RATE, "seconds_per_trial": seconds, "levels": list(LEVELS), "results": results,
           "criterion": f"every frame of every actor received (drivers solve every frame) and p99 send->receive "
                        f"latency < {1e3 / RATE:.2f} ms (first {WARMUP_S} s excluded)",
           "load_start": load, "load_end": os.getloadavg()[0],
           "data": "livecap generate seed 0: 60 markers, 43 shapes, 10 s take looped per actor"}
    _print(out)
    return out


def _print(out: dict) -> None:
    print(f"\nactors sustained at {out['rate_hz']:g} Hz ({out['criterion']}); load average "
          f"{out['load_start']:.2f} -> {out['load_end']:.2f}")
    print(f"{'mode':16s} {'layout':18s} {'actors':>6s} {'p99 ms at max':>14s} {'driver CPU':>10s} {'first failure':s}")
    for r in out["results"]:
        ok = [t for t in r["trials"] if t["sustained"] and t["actors"] == r["sustained_actors"]]
        bad = [t for t in r["trials"] if not t["sustained"]]
        fail = (f"N={bad[-1]['actors']}: received {bad[-1]['received_min']}/{bad[-1]['sent_per_actor']}, "
                f"stale {bad[-1]['stale']}, p99 {bad[-1]['p99_ms']:.1f} ms") if bad else "-"
        p99 = f"{ok[-1]['p99_ms']:.2f}" if ok else "-"
        cpu = f"{ok[-1]['driver_cpu_pct']:.0f}%" if ok else "-"
        print(f"{r['mode']:16s} {_layout_name(r['layout']):18s} {r['sustained_actors']:6d} {p99:>14s} {cpu:>10s} "
              f"{fail}")


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__, modes="qp,movement-stream", layouts="1,2,per-actor"))
