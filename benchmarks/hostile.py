"""A live session under attack (issue 17), across real processes on loopback.

Flood: benchmarks/hostile_traffic.py streams valid frames at 120 Hz to ``livecap run`` with about
10^5 malformed messages interleaved (ZeroMQ and OSC), or 400 packets each announcing a new 40 KB
layout (ZeroMQ); the baseline row streams the same valid frames alone, in the same run. Reported:
valid frames solved, stale skips, what was counted, and the driver's resident memory (VmRSS)
sampled after the first second and at the end of the stream.

Subscribers: ``livecap send --clock monotonic`` -> ``livecap run --zmq-out`` -> a healthy
subscriber that measures latency (receive time - send time) beside a dead one (SIGSTOPped) and
a slow one (one message per 50 ms), for each ``--zmq-policy``; the baseline is the healthy
subscriber alone.

Eviction (issue 36.1): an honest ``livecap send --connect`` beside benchmarks/layout_burst.py, both
connected to ``livecap run --zmq-in-bind``; rows alternate no attack / attack in the same run.
Garbage (issue 36.10): ZeroMQ rows with and without the malformed flood, ``--skip-stale`` on,
alternating, with the driver's CPU time.

    python -m benchmarks.hostile [--quick] [--parts floods,subscribers,eviction,garbage]
"""

from __future__ import annotations

import json
import os
import re
import signal
import tempfile
import textwrap
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks.processes import first_line, free_port, spawn
from benchmarks.timing import suite_main, table

RATE = 120.0

SUBSCRIBER = """
import json, sys, time, msgpack, zmq
addr, out, idle, delay = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
s = zmq.Context().socket(zmq.SUB)
s.setsockopt(zmq.RCVHWM, 100)
if delay:  # a small kernel buffer: the stuck/slow reader's backlog reaches the driver's high-water mark
    s.setsockopt(zmq.RCVBUF, 4096)
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
    if msg.get("type") == "weights":
        lat.append(now - msg["timestamp"])
    if delay:
        time.sleep(delay)
json.dump(lat, open(out, "w"))
"""


def _rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


class RssSampler(threading.Thread):
    """VmRSS of a process every 0.1 s: the value one second after start, the last, the peak."""

    def __init__(self, pid: int) -> None:
        super().__init__(daemon=True)
        self.pid, self.samples, self.done = pid, [], threading.Event()

    def run(self) -> None:
        t0 = time.monotonic()
        while not self.done.wait(0.1):
            r = _rss_mb(self.pid)
            if np.isfinite(r):
                self.samples.append((time.monotonic() - t0, r))

    def summary(self) -> dict:
        after1 = [r for t, r in self.samples if t >= 1.0] or [r for _, r in self.samples]
        return {"rss_start_mb": after1[0], "rss_end_mb": after1[-1], "rss_peak_mb": max(after1)}


def flood(work: Path, kind: str, valid: int, garbage: int, layout_flood: int = 0, skip_stale: bool = True) -> dict:
    """One session under one attack. ``skip_stale`` off: every valid frame must be solved, so
    ``solved`` shows whether garbage starved any; on (the live default): ``stale`` counts only
    valid frames skipped because a newer valid one was waiting (the machine's load decides how many)."""
    port = free_port()
    prof = work / "profile.npz"
    take = work / "demo_take.c3d"
    stats = work / f"{kind}-{garbage}-{layout_flood}-{skip_stale}.json"
    src = ["--zmq-in", f"tcp://127.0.0.1:{port}"] if kind == "zmq" else ["--osc-in", f"127.0.0.1:{port}"]
    addr = f"tcp://127.0.0.1:{port}" if kind == "zmq" else f"127.0.0.1:{port}"
    if kind == "zmq":  # the sender binds; the driver connects
        sender = spawn(["-m", "benchmarks.hostile_traffic", kind, addr, take, "--valid", valid, "--rate", RATE,
                        "--garbage", garbage, "--layout-flood", layout_flood])
        first_line(sender)
    run = spawn(["-m", "livecap", "run", *src, "--profile", prof, "--idle-timeout", 2.0, "--stats-file", stats,
                 "--skip-stale" if skip_stale else "--no-skip-stale"])
    first_line(run)
    sampler = RssSampler(run.pid)
    sampler.start()
    if kind == "osc":
        sender = spawn(["-m", "benchmarks.hostile_traffic", kind, addr, take, "--valid", valid, "--rate", RATE,
                        "--garbage", garbage])
        first_line(sender)
    out, err = sender.communicate(timeout=valid / RATE + 300)
    sent = json.loads(out.strip().splitlines()[-1])
    run.communicate(timeout=120)
    sampler.done.set()
    sampler.join()
    st = json.loads(stats.read_text())
    bad = st["bad_input"]
    attack = "none" if not garbage and not layout_flood else (
        f"{sent['garbage']} malformed" if garbage else f"{sent.get('layouts', 0)} x 40 KB layouts")
    return {"source": kind, "attack": attack, "skip_stale": "on" if skip_stale else "off",
            "valid_sent": sent["valid"], "received": st["frames_in"], "solved": st["frames_out"],
            "solved_pct": 100.0 * st["frames_out"] / sent["valid"], "stale": st["stale"],
            "bad_counted": sum(v for k, v in bad.items() if k not in ("stream_restart", "missing")),
            "driver_cpu_s": st["cpu_seconds"], "receive_p99_ms": st["timing"]["receive"]["p99_ms"],
            "solve_p50_ms": st["timing"]["solve"]["p50_ms"], **sampler.summary()}


def eviction(work: Path, valid: int, burst: int) -> dict:
    """Issue 36.1: ``livecap run --zmq-in-bind`` fed by an honest ``livecap send --connect`` (labels
    once a second, the layout id in between) beside benchmarks/layout_burst.py sending ``burst``
    fresh layouts at once every second (0: no attacker, the baseline). ``--no-skip-stale``, so
    ``published`` counts every honest frame the session accepted, whatever the machine's load."""
    addr = f"tcp://127.0.0.1:{free_port()}"
    stats = work / f"evict-{burst}.json"
    run = spawn(["-m", "livecap", "run", "--zmq-in", addr, "--zmq-in-bind", "--profile", work / "profile.npz",
                 "--idle-timeout", 2.0, "--no-skip-stale", "--stats-file", stats])
    first_line(run)
    attacker = None
    if burst:
        attacker = spawn(["-m", "benchmarks.layout_burst", addr, "--burst", burst, "--seconds", valid / RATE + 3])
        first_line(attacker)
    sender = spawn(["-m", "livecap", "send", work / "demo_take.c3d", "--zmq", addr, "--connect", "--loop",
                    "--frames", valid])
    sender.communicate(timeout=valid / RATE + 120)
    sent = json.loads(attacker.communicate(timeout=60)[0].strip().splitlines()[-1]) if attacker else {}
    run.communicate(timeout=120)
    st = json.loads(stats.read_text())
    bad = st["bad_input"]
    return {"attack": f"{burst} fresh layouts/s" if burst else "none", "attack_packets": sent.get("packets", 0),
            "attack_kB_s": sent.get("bytes", 0) / 1e3 / max(sent.get("seconds", 1.0), 1e-9), "honest_sent": valid,
            "published": st["frames_out"], "published_pct": 100.0 * st["frames_out"] / valid,
            "unknown_layout": bad.get("unknown_layout", 0), "unknown_label": bad.get("unknown_label", 0)}


def subscribers(work: Path, policy: str, frames: int, others: bool) -> dict:
    port = free_port()
    run = spawn(["-m", "livecap", "run", "--zmq-in", f"tcp://127.0.0.1:{port}", "--zmq-out", "0", "--zmq-policy",
                 policy, "--profile", work / "profile.npz", "--idle-timeout", 2.0, "--stats-file",
                 work / f"sub-{policy}-{others}.stats.json"])
    out_addr = re.search(r"zmq-out ([^;\s]+)", first_line(run)).group(1)
    sub = textwrap.dedent(SUBSCRIBER)
    healthy = spawn(["-c", sub, out_addr, work / "healthy.json", 3.0, 0.0])
    procs = [healthy]
    if others:
        dead = spawn(["-c", sub, out_addr, work / "dead.json", 3.0, 1.0])
        slow = spawn(["-c", sub, out_addr, work / "slow.json", 3.0, 0.05])
        procs += [dead, slow]
    for p in procs:
        first_line(p)
    if others:
        os.kill(dead.pid, signal.SIGSTOP)
    sender = spawn(["-m", "livecap", "send", work / "demo_take.c3d", "--zmq", f"tcp://127.0.0.1:{port}", "--loop",
                    "--clock", "monotonic", "--frames", frames, "--labels-every", 0])
    sender.communicate(timeout=frames / RATE + 120)
    healthy.communicate(timeout=60)
    run.communicate(timeout=60)
    if others:
        for p in (dead, slow):
            os.kill(p.pid, signal.SIGCONT)
            p.kill()
            p.communicate()
    lat = np.asarray(json.loads((work / "healthy.json").read_text())) * 1e3
    st = json.loads((work / f"sub-{policy}-{others}.stats.json").read_text())
    p50, p99 = np.percentile(lat, [50, 99]) if len(lat) else (float("nan"), float("nan"))
    return {"policy": policy, "beside": "dead + slow" if others else "alone", "published": st["frames_out"],
            "healthy_received": int(len(lat)), "healthy_pct": 100.0 * len(lat) / max(st["frames_out"], 1),
            "p50_ms": float(p50), "p99_ms": float(p99),
            "sink_drops": sum(s.get("drops", 0) for s in st["sinks"].values())}


def run(quick: bool = False, parts: tuple[str, ...] = ("floods", "subscribers", "eviction")) -> dict:
    """Measure ``parts``; ``quick`` streams 5 s per row instead of 20 s."""
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.demo import DEMO_TAKE, generate
    from livecap.demo.performance import PerformanceSettings
    from transport.takefile import read_take

    valid = int((5 if quick else 20) * RATE)
    per_frame = int(np.ceil(1e5 / valid))  # about 10^5 malformed messages per flood row
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        generate(work, 0, PerformanceSettings(seconds=10, rate=RATE, seed=1))
        rig = Rig.load(work / "demo_rig.npz")
        layout = MarkerLayout.load(work / "demo_rig.markers.json", rig)
        take = read_take(work / DEMO_TAKE).select(layout.labels)
        calibrate(rig, layout, estimate_neutral(take, layout.stable, 120)).save(work / "profile.npz")
        if DEMO_TAKE != "demo_take.c3d":
            (work / "demo_take.c3d").symlink_to(work / DEMO_TAKE)
        floods = []
        for kind in ("zmq", "osc") if "floods" in parts else ():
            for garbage, skip in ((0, False), (per_frame, False), (0, True), (per_frame, True)):
                floods.append(flood(work, kind, valid, garbage, skip_stale=skip))
        if "floods" in parts:
            floods.append(flood(work, "zmq", valid, 0, layout_flood=400, skip_stale=False))
        subs = [subscribers(work, policy, valid, others) for policy in ("fair", "count") for others in (False, True)
                if "subscribers" in parts]
        evictions = [eviction(work, valid, burst) for burst in (0, 20, 0, 20)] if "eviction" in parts else []
        # issue 36.10: does decoding garbage on the frame thread put the solver behind? alternating rows, same run
        garbage = [flood(work, "zmq", valid, g) for g in (0, per_frame, 0, per_frame) if "garbage" in parts]
    out = {"rate_hz": RATE, "valid_frames": valid, "floods": floods, "subscribers": subs, "eviction": evictions,
           "garbage": garbage,
           "machine": f"{os.cpu_count()} CPUs (shared VM), load average {load:.2f} at start, "
                      f"{os.getloadavg()[0]:.2f} at the end",
           "data": "livecap generate seed 0: 60 markers, 43 shapes, 10 s take looped, --profile, mode lsq"}
    print(table(floods, ["source", "attack", "skip_stale", "valid_sent", "received", "solved", "solved_pct", "stale",
                         "bad_counted", "driver_cpu_s", "receive_p99_ms", "solve_p50_ms",
                         "rss_start_mb", "rss_end_mb", "rss_peak_mb"], f"flood at {RATE:g} Hz ({out['machine']})"))
    print(table(subs, ["policy", "beside", "published", "healthy_received", "healthy_pct", "p50_ms", "p99_ms",
                       "sink_drops"], "healthy subscriber beside a dead (SIGSTOP) and a slow (20 msg/s) one"))
    print(table(garbage, ["attack", "valid_sent", "solved", "solved_pct", "stale", "driver_cpu_s", "receive_p99_ms",
                          "solve_p50_ms"], "ZeroMQ garbage flood, --skip-stale, alternating rows"))
    print(table(evictions, ["attack", "attack_packets", "attack_kB_s", "honest_sent", "published", "published_pct",
                            "unknown_layout", "unknown_label"], "honest livecap send beside a layout-eviction burst"))
    return out


def capture_session(work: Path, system: str, frames: int, hostile: bool, points: int = 0,
                    tree: Path | None = None) -> dict:
    """One ``livecap run --natnet-in/--qtm-in`` (from ``tree``, default this one) against the fake
    server of tests/capture_servers.py streaming the demo actor's neutral at 120 Hz."""
    import subprocess
    import sys

    servers = Path(__file__).resolve().parents[1] / "tests" / "capture_servers.py"
    server = spawn([servers, system, frames, "--face", work / "face.json", "--rate", RATE, "--points", points,
                    *(["--hostile"] if hostile else [])])
    port = int(first_line(server))
    stats = work / f"capture-{system}-{hostile}-{points}-{tree is not None}.json"
    args = ["-m", "livecap", "run", f"--{system}-in", f"127.0.0.1:{port}", "--profile", work / "profile.npz",
            "--mode", "lsq", "--idle-timeout", 2.0, "--stats-file", stats, *(["--unlabelled"] if points else [])]
    if tree is None:
        run = spawn(args)
    else:
        run = subprocess.Popen([sys.executable, *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env={**os.environ, "PYTHONPATH": str(tree)}, cwd=tree)
    try:
        first_line(run)
    except RuntimeError:
        server.kill()
        raise
    sampler = RssSampler(run.pid)
    sampler.start()
    out, _ = server.communicate(timeout=frames / RATE + 120)
    sent = json.loads(out.strip().splitlines()[-1])
    _, err = run.communicate(timeout=120)
    sampler.done.set()
    sampler.join()
    st = json.loads(stats.read_text()) if stats.exists() else {"frames_in": 0, "frames_out": 0, "stale": 0,
                                                                  "bad_input": {}, "timing": {}}
    recv = st["timing"].get("receive", {})
    return {"source": system + (f" unlabelled {points} pts" if points else ""),
            "code": "main" if tree else "this", "attack": f"{sent['hostile']} hostile" if hostile else "none",
            "sent": sent["frames"], "received": st["frames_in"], "published": st["frames_out"],
            "published_pct": 100.0 * st["frames_out"] / max(sent["frames"], 1), "stale": st["stale"],
            "bad_counted": sum(v for k, v in st["bad_input"].items() if k != "stream_restart"),
            "exit": run.returncode, "receive_p99_ms": recv.get("p99_ms", float("nan")),
            "receive_max_ms": recv.get("max_ms", float("nan")), **sampler.summary()}


def capture_floods(quick: bool = False, against: str | None = None) -> dict:
    """Issue 36: NatNet and QTM clients fed honest frames, then the same with hostile packets among
    them (every fifth frame), and NatNet unlabelled clouds of the face alone against the face among
    2340 ghosts (720 frames, the issue's case). ``against``: a checkout (e.g. /work/main) whose
    driver runs the honest and cloud rows too, in the same run (not the hostile NatNet row: its
    reader allocates up to 4.1 GB per packet there)."""
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from transport.takefile import read_take

    root = Path(__file__).resolve().parents[1] / "recordings"
    frames = 240 if quick else 1200
    load = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        rig = Rig.load(root / "demo_rig.npz")
        layout = MarkerLayout.load(root / "demo_rig.markers.json", rig)
        take = read_take(root / "demo_neutral.c3d").select(layout.labels)
        profile = calibrate(rig, layout, estimate_neutral(take, layout.stable, 120))
        profile.save(work / "profile.npz")
        (work / "face.json").write_text(json.dumps({lab: [float(v) for v in p] for lab, p in
                                                    zip(profile.labels, profile.source_neutral, strict=True)}))
        trees = [None] + ([Path(against)] if against else [])
        for tree in trees:
            for system in ("natnet", "qtm"):
                for hostile in (False, True):
                    if hostile and system == "natnet" and tree is not None:
                        continue
                    rows.append(capture_session(work, system, frames, hostile, tree=tree))
            for points in (60, 2400):
                rows.append(capture_session(work, "natnet", 240 if quick else 720, False, points, tree))
    out = {"rate_hz": RATE, "rows": rows,
           "machine": f"{os.cpu_count()} CPUs (shared VM), load average {load:.2f} at start, "
                      f"{os.getloadavg()[0]:.2f} at the end",
           "data": "recordings/demo_neutral.c3d calibrated on the demo rig; its neutral streamed (breathing 0.1 mm) "
                   "by tests/capture_servers.py; mode lsq"}
    print(table(rows, ["source", "code", "attack", "sent", "received", "published", "published_pct", "stale",
                       "bad_counted", "exit", "receive_p99_ms", "receive_max_ms", "rss_start_mb", "rss_end_mb",
                       "rss_peak_mb"], f"capture clients at {RATE:g} Hz ({out['machine']})"))
    return out


if __name__ == "__main__":
    import sys

    if sys.argv[1:2] == ["capture"]:  # python -m benchmarks.hostile capture [--quick] [--against DIR] [--json F]
        sys.argv.pop(1)
        sys.exit(suite_main(lambda quick, against=("",): capture_floods(quick, against[0] or None),
                            capture_floods.__doc__, against=""))
    sys.exit(suite_main(run, __doc__, parts="floods,subscribers,eviction"))
