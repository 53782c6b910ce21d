"""End-to-end live latency: a marker packet sent by one process -> weights received by a third.

Three processes per measurement, as in a real session: ``livecap send`` streams a looped
demo take at 120 Hz over ZeroMQ stamping each packet with the machine's monotonic clock;
``livecap run`` (the driver) solves and publishes; a subscriber computes ``now - timestamp``
for every weights message. In the same run, the same marker payloads take the same two hops
through a bare relay (SUB -> PUB, no decoding, no solve): the floor ZeroMQ itself sets. The
driver's CPU use comes from the kernel's rusage of its process (user + system time / wall).

    python -m benchmarks.live_latency [--quick] [--modes qp,movement-stream,...] [--runs N] [--takes demo,S07-001]

``--takes``: ``demo`` is a generated 10 s demo take (60 markers, 43 shapes); any other name is the real performance
``realdata/performance/<name>.csv`` driving the ICT rig (``livecap.demo.curves_take``: 60 markers, 53 shapes, its
first 20 s at 60 Hz sent at twice its speed, so 120 packets a second; 0.5 mm noise, 5 % occluded) with the plain
profile ``livecap realeval`` uses. Every take gets its own bare relay in each run.

The driver runs with the defaults of a live source, so ``--skip-stale`` is on: a mode slower
than 120 Hz (lsq) skips frames (the ``stale`` column) rather than falling behind without bound.

Each run measures the bare relay and then every mode; with ``--runs N`` (default 3; 1 with ``--quick``) the tables
hold the medians over runs of each p99 (and of each run's p99 / that run's bare p99), as issue
18 asks. The driver's own per-frame time comes from its stats file: ``frame`` = everything it
does for a solved frame (decode, stabilise, the mode's step, every sink), ``around_step`` = that
less the mode's step (what the driver adds, separable from the solver's speed).
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

RECEIVER = """
import json, sys, time, msgpack, zmq
addr, out, idle = sys.argv[1], sys.argv[2], float(sys.argv[3])
s = zmq.Context().socket(zmq.SUB)
s.connect(addr)
s.setsockopt(zmq.SUBSCRIBE, b"")
time.sleep(0.5)
print("ready", flush=True)
lat, last = [], None
while True:
    if not s.poll(int(idle * 1000)):
        if last is not None:
            break
        continue
    parts = s.recv_multipart()
    now = time.monotonic()
    msg = msgpack.unpackb(parts[-1])
    last = now
    if msg.get("type") in ("weights", "markers"):
        lat.append(now - msg["timestamp"])
json.dump(lat, open(out, "w"))
"""

RELAY = """
import sys, zmq
ctx = zmq.Context()
sub, pub = ctx.socket(zmq.SUB), ctx.socket(zmq.PUB)
sub.connect(sys.argv[1])
sub.setsockopt(zmq.SUBSCRIBE, b"")
pub.bind("tcp://127.0.0.1:*")
print(pub.getsockopt(zmq.LAST_ENDPOINT).decode(), flush=True)
while True:
    pub.send_multipart(sub.recv_multipart())
"""










def _stats(lat: list[float], sent: int) -> dict:
    a = np.asarray(lat) * 1e3
    if not len(a):
        return {"received": 0, "sent": sent}
    p50, p99 = np.percentile(a, [50, 99])
    return {"sent": sent, "received": int(len(a)), "p50_ms": float(p50), "p99_ms": float(p99),
            "max_ms": float(a.max())}


def _send(take: Path, port: int, frames: int, speed: float = 1.0) -> subprocess.Popen:
    return spawn(["-m", "livecap", "send", take, "--zmq", f"tcp://127.0.0.1:{port}", "--loop", "--clock",
                   "monotonic", "--frames", frames, "--labels-every", 0, "--speed", speed])


def bare(take: Path, frames: int, work: Path, speed: float = 1.0) -> dict:
    """Sender -> bare relay -> receiver: the same payloads and hops without livecap in between."""
    port = free_port()
    relay = spawn(["-c", textwrap.dedent(RELAY), f"tcp://127.0.0.1:{port}"])
    relay_out = first_line(relay)
    rx = spawn(["-c", textwrap.dedent(RECEIVER), relay_out, work / "bare.json", 2.0])
    first_line(rx)
    sender = _send(take, port, frames, speed)
    sender.communicate(timeout=frames / RATE + 120)
    rx.communicate(timeout=60)
    relay.kill()
    relay.communicate()
    return _stats(json.loads((work / "bare.json").read_text()), frames)


def driver(take: Path, profile: Path, mode: str, frames: int, work: Path, extra: tuple = (),
           speed: float = 1.0) -> dict:
    """``livecap run`` with its defaults for a live ZeroMQ source (``--skip-stale`` on: a solver
    slower than the stream skips frames, counted as stale, instead of falling ever further behind)."""
    port = free_port()
    run = spawn(["-m", "livecap", "run", "--zmq-in", f"tcp://127.0.0.1:{port}", "--zmq-out", "0", "--profile",
                  profile, "--mode", mode, "--idle-timeout", 2.0, "--stats-file", work / f"{mode}.stats.json",
                  *extra])
    out_addr = re.search(r"zmq-out ([^;\s]+)", first_line(run)).group(1)
    rx = spawn(["-c", textwrap.dedent(RECEIVER), out_addr, work / f"{mode}.json", 3.0])
    first_line(rx)
    t0 = time.monotonic()
    sender = _send(take, port, frames, speed)
    sender.communicate(timeout=frames / RATE + 600)
    _, status, usage = os.wait4(run.pid, 0)
    wall = time.monotonic() - t0
    run.returncode = os.waitstatus_to_exitcode(status)
    run.communicate()
    rx.communicate(timeout=60)
    out = _stats(json.loads((work / f"{mode}.json").read_text()), frames)
    st = json.loads((work / f"{mode}.stats.json").read_text())
    out.update(mode=mode, driver_cpu_s=usage.ru_utime + usage.ru_stime, wall_s=wall,
               # the solve loop's CPU (from the driver's own stats) per second of stream; startup excluded
               driver_cpu_pct=100 * st["cpu_seconds"] / (frames / RATE),
               driver_cpu_with_startup_pct=100 * (usage.ru_utime + usage.ru_stime) / wall,
               solve_p50_ms=st["timing"]["solve"]["p50_ms"], solve_p99_ms=st["timing"]["solve"]["p99_ms"],
               **{f"{k}_{q}_ms": st["timing"].get(k, {}).get(f"{q}_ms", float("nan"))
                  for k in ("step", "frame", "around_step") for q in ("p50", "p99")},
               frames_in=st["frames_in"], stale=st.get("stale", 0),
               drops=sum(s.get("drops", 0) for s in st["sinks"].values()))
    return out


MODES = ("qp", "movement-stream", "robust", "rbf", "lsq")


def _median_of_runs(runs: list[dict]) -> dict:
    """Per-key median over runs of every number (p99s, CPU, ...); the per-run p99s kept beside."""
    out = dict(runs[-1])
    for k, v in runs[-1].items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            vals = [r[k] for r in runs if isinstance(r.get(k), (int, float))]
            out[k] = float(np.median(vals)) if vals else v
    out["p99_ms_runs"] = [r.get("p99_ms", float("nan")) for r in runs]
    return out


def _real_take(name: str, work: Path) -> tuple[Path, Path, float]:
    """A real performance driving the ICT rig: take file, profile file and the send speed for RATE packets a second."""
    from benchmarks.realperf import ict_performance
    from livecap.demo.curves_take import CurveTakeSettings
    from transport.takefile import write_take

    _, _, ct, profile, _ = ict_performance(name, CurveTakeSettings(seconds=20.0))
    write_take(ct.take, work / f"{name}.c3d")
    profile.save(work / f"{name}.profile.npz")
    return work / f"{name}.c3d", work / f"{name}.profile.npz", RATE / ct.take.rate


def run(quick: bool = False, modes=MODES, runs=("",), takes=("demo",)) -> dict:
    """Measure; ``quick`` streams 10 s instead of 60 s; ``runs`` repeats bare + every mode (default
    3, 1 when quick). The demo take's figures are ``bare_zmq`` and ``modes``; another take's are under
    ``takes[name]``."""
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.demo import DEMO_TAKE, generate
    from livecap.demo.performance import PerformanceSettings
    from livecap.demo.rom import generate_rom
    from transport.takefile import read_take

    seconds = 10 if quick else 60
    given = runs[0] if isinstance(runs, (tuple, list)) else runs
    n_runs = max(1, int(given)) if str(given).strip() else (1 if quick else 3)
    modes = tuple(m for m in modes if m)
    takes = tuple(t for t in takes if t) or ("demo",)
    load = os.getloadavg()[0]
    frames = int(seconds * RATE)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        sources, extra = {}, {}
        if "demo" in takes:
            generate(work, 0, PerformanceSettings(seconds=10, rate=RATE, seed=1))
            rig = Rig.load(work / "demo_rig.npz")
            layout = MarkerLayout.load(work / "demo_rig.markers.json", rig)
            take = read_take(work / DEMO_TAKE).select(layout.labels)
            calibrate(rig, layout, estimate_neutral(take, layout.stable, 120)).save(work / "profile.npz")
            sources["demo"] = (work / DEMO_TAKE, work / "profile.npz", 1.0)
            if "rbf" in modes:  # key pairs from the demo range-of-motion take (livecap rom)
                keys = next(p for p in generate_rom(work / "rom", rig, layout, PerformanceSettings(rate=RATE, seed=50))
                            if p.name.endswith(".keys.json"))
                extra["rbf"] = ("--option", f"keys={keys}")
        for t in takes:
            if t != "demo":
                sources[t] = _real_take(t, work)
        per_run = {t: [] for t in takes}
        for i in range(n_runs):
            for t in takes:
                take_path, profile_path, speed = sources[t]
                floor = bare(take_path, frames, work, speed)
                res = {m: driver(take_path, profile_path, m, frames, work, extra.get(m, ()) if t == "demo" else (),
                                 speed) for m in modes}
                for r in res.values():
                    r["p99_over_bare"] = r.get("p99_ms", float("nan")) / floor.get("p99_ms", float("nan"))
                per_run[t].append({"bare_zmq": floor, "modes": res, "load": os.getloadavg()[0]})
                print(f"run {i + 1}/{n_runs}, {t}: bare p99 {floor.get('p99_ms', float('nan')):.3f} ms; " + ", ".join(
                    f"{m} p99 {r.get('p99_ms', float('nan')):.3f} ms ({r['p99_over_bare']:.2f}x), driver frame p99 "
                    f"{r['frame_p99_ms']:.3f} ms, around step {r['around_step_p99_ms']:.3f} ms"
                    for m, r in res.items()), flush=True)

    def medians(t: str) -> dict:
        return {"bare_zmq": _median_of_runs([r["bare_zmq"] for r in per_run[t]]),
                "modes": {m: _median_of_runs([r["modes"][m] for r in per_run[t]]) for m in modes},
                "per_run": per_run[t]}

    out = {"rate_hz": RATE, "seconds": seconds, "runs": n_runs,
           **(medians("demo") if "demo" in takes else {}),
           "takes": {t: medians(t) for t in takes if t != "demo"},
           "machine": f"{os.cpu_count()} CPUs, load average {load:.2f} at start, {os.getloadavg()[0]:.2f} at the end",
           "load_start": load, "load_end": os.getloadavg()[0],
           "data": "demo: livecap generate seed 0: 60 markers, 43 shapes, 10 s take looped; rbf keys from livecap "
                   "rom; other takes: a real performance driving the ICT rig (60 markers, 53 shapes), 20 s looped"}
    for t in takes:
        _print({**out, **(medians(t) if t != "demo" else {})}, t)
    return out


def _print(out: dict, take: str = "demo") -> None:
    b = out["bare_zmq"]
    print(f"live latency, {take} take, marker packet sent -> weights received, {out['rate_hz']:g} Hz for "
          f"{out['seconds']} s, medians over {out.get('runs', 1)} run(s) ({out['machine']})")
    print(f"{'path':16s} {'recv/sent':>11s} {'stale':>6s} {'p50 ms':>8s} {'p99 ms':>8s} {'p99/bare':>9s} "
          f"{'frame p99':>10s} {'w/o step':>9s} {'step p99':>9s} {'driver CPU':>10s}")
    print(f"{'bare zmq':16s} {b['received']:>5.0f}/{b['sent']:<5.0f} {'':>6s} {b.get('p50_ms', float('nan')):8.3f} "
          f"{b.get('p99_ms', float('nan')):8.3f} {1.0:9.2f}")
    for m, r in out["modes"].items():
        ratio = r.get("p99_over_bare", r.get("p99_ms", float("nan")) / b.get("p99_ms", float("nan")))
        print(f"{m:16s} {r['received']:>5.0f}/{r['sent']:<5.0f} {r.get('stale', 0):6.0f} "
              f"{r.get('p50_ms', float('nan')):8.3f} {r.get('p99_ms', float('nan')):8.3f} {ratio:9.2f} "
              f"{r.get('frame_p99_ms', float('nan')):10.3f} {r.get('around_step_p99_ms', float('nan')):9.3f} "
              f"{r.get('step_p99_ms', float('nan')):9.3f} {r['driver_cpu_pct']:9.1f}%")
    print("p99/bare = median over runs of each run's p99 / that run's bare p99; frame = the driver's own time for "
          "a solved frame (decode to last sink, ms), w/o step = frame less the mode's step; driver CPU = the solve "
          "loop's CPU time per second of stream (startup excluded); stale = frames skipped because a newer one "
          "was waiting")


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__, modes=",".join(MODES), runs="", takes="demo"))
