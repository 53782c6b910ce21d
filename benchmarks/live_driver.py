"""The live driver's own per-frame CPU, in one process: packet bytes -> decode -> stabilise -> the
mode's step -> SolveResult -> ZeroMQ sink (a subscriber attached), paced at 120 Hz.

Thread CPU time (``time.thread_time``) per part, so the figures are steadier than the three-process
wall-clock run of ``live_latency`` on a shared machine, and the mode's step is separable from what
the driver adds around it (issue 18 item 4):

    python -m benchmarks.live_driver [--quick] [--modes robust,qp] [--waits sleep,spin1ms,spin,none]
                                     [--takes demo,S07-001]

``--takes``: ``demo`` is a generated 10 s demo take (60 markers, 43 shapes, 2 % missing); any other name is the
real performance ``realdata/performance/<name>.csv`` driving the ICT rig (``livecap.demo.curves_take``: 60 markers,
53 shapes, its first 20 s, 0.5 mm noise, 5 % occluded in bursts, a stable marker lost for 1 s) with the plain
profile ``livecap realeval`` uses. Each take is looped to the number of frames.

``--waits``: how the loop waits for the next 120 Hz deadline between frames (what the driver does while
no packet is due): ``sleep`` in the kernel until it (the driver's own blocking poll behaves so),
``spin1ms`` sleeps until 1 ms before it and then busy-polls the subscriber socket, ``spin`` busy-polls
the whole interval, ``none`` runs the frames back to back (the tight-loop cost, no pacing). The waits
of one run alternate frame blocks, so the load falls on each alike.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.timing import suite_main

PARTS = ("decode", "stabilise", "step", "publish", "frame", "around_step")
WAITS = ("sleep", "spin1ms", "spin", "none")
BLOCK = 120  # frames per block of one wait; the waits take turns block by block


def _wait(how: str, deadline: float, rx) -> None:
    """Until ``deadline`` (time.perf_counter seconds), the way ``how`` says (see the module's doc)."""
    now = time.perf_counter()
    if how == "none" or now >= deadline:
        return
    if how == "sleep":
        time.sleep(deadline - now)
        return
    if how == "spin1ms" and deadline - now > 1e-3:
        time.sleep(deadline - now - 1e-3)
    while time.perf_counter() < deadline:
        while rx.poll(0):
            rx.recv()


def _take_and_profile(name: str):
    """The take to stream and the actor's profile: the generated demo, or a real performance on the ICT rig."""
    if name != "demo":
        from benchmarks.realperf import ict_performance
        from livecap.demo.curves_take import CurveTakeSettings

        _, _, ct, profile, _ = ict_performance(name, CurveTakeSettings(seconds=20.0))
        return ct.take, profile
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.demo import DEMO_TAKE, generate
    from livecap.demo.performance import PerformanceSettings
    from transport.takefile import read_take

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        generate(work, 0, PerformanceSettings(seconds=10, rate=120.0, seed=1))
        rig = Rig.load(work / "demo_rig.npz")
        layout = MarkerLayout.load(work / "demo_rig.markers.json", rig)
        take = read_take(work / DEMO_TAKE)
        return take, calibrate(rig, layout, estimate_neutral(take.select(layout.labels), layout.stable, 120))


def measure(mode: str, frames: int, pace: float = 1 / 120, waits: tuple[str, ...] = ("sleep",),
            take_name: str = "demo") -> dict:
    """Per wait, per-part thread-CPU p50 / p99 (µs) of ``frames`` frames of a take (``_take_and_profile``) through
    the driver's own path."""
    import zmq

    from livecap.live.pipeline import Pipeline
    from transport.wire import encode_markers, layout_id, topic
    from transport.zmq_sink import ZmqSink
    from transport.zmq_source import ZmqSource

    take, profile = _take_and_profile(take_name)
    lid = layout_id(take.labels)
    loop = list(take.frames())
    total = frames * len(waits)  # numbered on across the take's loops: one stream, no restarts
    packets = [[topic("markers", "actor"), encode_markers(i, i * pace, f.positions, f.valid,
                                                          take.labels if i == 0 else None, lid)]
               for i, f in enumerate(loop[i % len(loop)] for i in range(total))]
    source = ZmqSource("tcp://127.0.0.1:1", profile.labels)
    sink = ZmqSink("tcp://127.0.0.1:*", rate=120.0)
    rx = zmq.Context.instance().socket(zmq.SUB)
    rx.connect(sink.address)
    rx.setsockopt(zmq.SUBSCRIBE, b"")
    time.sleep(0.3)
    pipe = Pipeline([], [sink], profile=profile, mode=mode)
    clock = time.thread_time
    spent: dict[str, float] = {}
    for name, obj, attr in (("stabilise", pipe._stabiliser, "step"), ("step", pipe._solver, "step")):
        inner = getattr(obj, attr)

        def timed(*args, _inner=inner, _name=name):
            c = clock()
            out = _inner(*args)
            spent[_name] = clock() - c
            return out

        setattr(obj, attr, timed)
    rows = {w: {p: [] for p in PARTS} for w in waits}
    deadline = time.perf_counter()
    for i, parts in enumerate(packets):
        how = waits[(i // BLOCK) % len(waits)]
        c0 = clock()
        frame = source.decode(parts)
        c1 = clock()
        result = pipe.solve_frame(frame)
        c2 = clock()
        pipe.publish(result)
        c3 = clock()
        for p, v in (("decode", c1 - c0), ("publish", c3 - c2), ("frame", c3 - c0), ("stabilise", spent["stabilise"]),
                     ("step", spent["step"]), ("around_step", c3 - c0 - spent["step"])):
            rows[how][p].append(v)
        while rx.poll(0):
            rx.recv()
        deadline = max(deadline + pace, time.perf_counter() - pace)  # a late frame does not start a burst
        _wait(how, deadline, rx)
    sink.close()
    rx.close(0)
    warm = min(frames // 10, BLOCK)  # the first block of each wait
    return {w: {p: {"p50_us": float(np.percentile(np.array(v[warm:]) * 1e6, 50)),
                    "p99_us": float(np.percentile(np.array(v[warm:]) * 1e6, 99))} for p, v in r.items()}
            for w, r in rows.items()}


def run(quick: bool = False, modes=("robust", "qp"), waits=("sleep",), takes=("demo",)) -> dict:
    """``out["modes"][mode]`` for the demo take, ``out["modes"]["<mode> <take>"]`` for a real performance."""
    frames = 1200 if quick else 7200
    waits = tuple(w for w in waits if w)
    if unknown := set(waits) - set(WAITS):
        raise SystemExit(f"unknown waits {sorted(unknown)} (choose from {', '.join(WAITS)})")
    load = os.getloadavg()
    out = {"frames": frames, "rate_hz": 120.0, "load_start": load, "clock": "thread CPU (time.thread_time)",
           "data": "demo: livecap generate seed 0 (60 markers, 43 shapes), 10 s take looped; other takes: a real "
                   "performance driving the ICT rig (60 markers, 53 shapes), its first 20 s looped",
           "waits": waits, "takes": [t for t in takes if t], "modes": {}}
    for t in (t for t in takes if t):
        for m in (m for m in modes if m):
            by_wait = measure(m, frames, waits=waits, take_name=t)
            key = m if t == "demo" else f"{m} {t}"
            out["modes"][key] = by_wait if len(waits) > 1 else by_wait[waits[0]]
            for w, r in by_wait.items():
                print(f"{key:18s} {w:8s} " + "  ".join(f"{p} {r[p]['p50_us']:.0f}/{r[p]['p99_us']:.0f}"
                                                       for p in PARTS) + "  (thread CPU µs p50/p99)", flush=True)
    out["load_end"] = os.getloadavg()
    print(f"load average {load[0]:.2f} -> {out['load_end'][0]:.2f}; frame = decode + stabilise + step + the rest "
          "of solve_frame + publish; around_step = frame less the mode's step")
    return out


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__, modes="robust,qp", waits="sleep", takes="demo"))
