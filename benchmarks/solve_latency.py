"""Per-frame solve latency of every registered mode at film-rig scales (54x50, 72x150, 72x1000, 120x1000).

Each mode is timed on the same synthetic stream (benchmarks/synthetic.py) through its ``step``
(what the live pipeline calls); the ratio column compares its p99 with plain unconstrained least
squares (a prefactored pseudo-inverse product) measured in the same run. Every mode in
livecap.modes.registry.MODES gets a row per size: timed, or the reason it is not.

* ``rbf`` needs key pairs: a synthetic range-of-motion key set (neutral + one key per shape,
  benchmarks.synthetic.rom_keys) is passed through the factory's ``keys`` option.
* ``movement`` is the offline whole-take solve (Seol et al. 2012 Eq. 5); its per-frame path is the
  sliding-window solver, timed as ``movement-stream``; offline timings are in the movement suite.
* ``lsq`` (scipy BVLS) is skipped at a size where a call takes more than ``SLOW_LIMIT_S``.
* ``movement-stream`` at 72 x 1000 (more shapes than marker coordinates) cannot be built with its
  default options (the shape prior leaves the system singular); it is timed with ``ridge=1e-3``
  and the row says so.

``peak_mb`` is the traced (Python + numpy) memory peak while building the solver and solving the
first frames, from tracemalloc (off while timing). Beside the wall-clock p50 / p99 each row has the
thread CPU time per call (``cpu_p50_us`` / ``cpu_p99_us``, time.thread_time_ns: what the call itself
cost, without the time another process held the core on a loaded machine) and the RMSE of the
weights against the synthetic ground truth on the stream's first ``rmse_frames`` frames from a reset
solver (300, or 60 for a mode slower than 0.1 s a call), the same frames in every run (accuracy beside speed).
"""

from __future__ import annotations

import os
import sys
import time
import tracemalloc

import numpy as np

from benchmarks.synthetic import rom_keys, synthetic_profile, synthetic_stream
from benchmarks.timing import suite_main, table
from livecap.modes.registry import MODES, build_solver

SIZES = [(54, 50), (72, 150), (72, 1000), (120, 1000)]
SLOW_LIMIT_S = 1.0
NOT_PER_FRAME = {"movement": "offline whole-take mode: per-frame path timed as movement-stream; "
                             "offline figures in the movement suite"}


def _options(mode: str, profile) -> dict:
    """Options some modes need to run on a bare synthetic profile."""
    if mode == "rbf":
        return {"keys": rom_keys(profile)}
    return {}


def _build(mode: str, profile) -> tuple[object, str]:
    """The solver, and a note when the default options had to be changed to build it at all."""
    opts = _options(mode, profile)
    try:
        return build_solver(mode, profile, opts), ""
    except Exception as exc:
        if mode != "movement-stream" or type(exc).__name__ != "IllPosedError":
            raise
    # more shapes than marker coordinates: the shape prior alone leaves G + K singular; a small ridge fixes it
    return build_solver(mode, profile, {**opts, "ridge": 1e-3}), "ridge=1e-3 (default options ill-posed: m > 3n)"


def time_steps(fn, n: int, warmup: int) -> dict:
    """``fn(i)`` for i in range(warmup + n): wall and thread-CPU microseconds per call (p50, p99, mean)."""
    for i in range(warmup):
        fn(i)
    wall, cpu = np.empty(n), np.empty(n)
    clock, thread = time.perf_counter_ns, time.thread_time_ns
    for k in range(n):
        c0, t0 = thread(), clock()
        fn(warmup + k)
        t1, c1 = clock(), thread()
        wall[k], cpu[k] = t1 - t0, c1 - c0
    wall /= 1e3
    cpu /= 1e3
    return {"n": n, "median_us": float(np.median(wall)), "p99_us": float(np.percentile(wall, 99)),
            "mean_us": float(wall.mean()), "cpu_p50_us": float(np.median(cpu)),
            "cpu_p99_us": float(np.percentile(cpu, 99)), "cpu_mean_us": float(cpu.mean())}


def accuracy(step, truth: np.ndarray, frames: int) -> dict:
    """RMSE of ``step(i)`` (i = 0 .. frames - 1, from a reset solver) against ``truth[i]``."""
    W = np.array([step(i) for i in range(frames)])
    return {"rmse": float(np.sqrt(np.mean((W - truth[:frames]) ** 2))), "rmse_frames": frames}


def _baseline(profile, targets, n: int, truth: np.ndarray | None = None) -> dict:
    pinv = np.linalg.pinv(profile.basis)
    flat = targets.reshape(len(targets), -1)
    res = time_steps(lambda i: pinv @ flat[i % len(flat)], n=n, warmup=100)
    if truth is not None:
        res.update(accuracy(lambda i: pinv @ flat[i], truth, min(len(flat), 300)))
    return res


def time_mode(mode: str, profile, targets, valid, count: int, warmup: int = 50,
              truth: np.ndarray | None = None) -> dict:
    """One mode at one size: build time, then median/p99 of ``step`` (or a reason it was skipped)."""
    if mode in NOT_PER_FRAME:
        return {"skipped": NOT_PER_FRAME[mode]}
    tracemalloc.start()  # numpy reports its buffers to tracemalloc: peak memory of build + first frames
    t0 = time.perf_counter()
    solver, note = _build(mode, profile)
    prepare = (time.perf_counter() - t0) * 1e3
    T = len(targets)
    probe = []
    for i in range(3):  # a slow mode is measured on a few calls before committing to thousands
        t1 = time.perf_counter()
        solver.step(targets[i], valid[i])
        probe.append(time.perf_counter() - t1)
    peak_mb = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()  # not while timing: it slows every allocation
    # the fastest probe: in a fresh checkout each of the first calls may compile a kernel (numba, ~1 s)
    per_call = float(np.min(probe))
    out = {"prepare_ms": prepare, "peak_mb": peak_mb, **({"note": note} if note else {})}
    if per_call > SLOW_LIMIT_S:
        return {**out, "skipped": f"{per_call:.1f} s per call (> {SLOW_LIMIT_S:g} s)"}
    if per_call > 0.01:  # milliseconds per call: fewer repetitions, same statistics
        count, warmup = max(30, min(count, int(20.0 / per_call))), 5
    res = time_steps(lambda i: solver.step(targets[i % T], valid[i % T]), n=count, warmup=warmup)
    if truth is not None:
        solver.reset()
        res.update(accuracy(lambda i: solver.step(targets[i], valid[i]), truth, min(T, 300 if per_call < 0.1 else 60)))
    return {**out, **res}


def run(quick: bool = False, modes: tuple[str, ...] = ()) -> dict:
    """``modes``: only these (default every registered mode)."""
    rows = []
    n_frames = 300 if quick else 3000
    count = 300 if quick else 3000
    load = os.getloadavg()[0]
    for n, m in SIZES:
        profile = synthetic_profile(n, m)
        targets, valid, truth = synthetic_stream(profile, n_frames)
        base = _baseline(profile, targets, 3 * count, truth)
        size = f"{n}x{m}"
        rows.append({"mode": "pinv (baseline)", "size": size, **base, "ratio_p99": 1.0})
        for mode in sorted(m for m in MODES if m in modes or not any(modes)):
            try:
                res = time_mode(mode, profile, targets, valid, count, truth=truth)
            except Exception as exc:  # a mode that cannot be built or run is reported, not hidden
                res = {"skipped": f"error: {type(exc).__name__}: {str(exc)[:80]}"}
            if "p99_us" in res:
                res["ratio_p99"] = res["p99_us"] / base["p99_us"]
            rows.append({"mode": mode, "size": size, **res})
    print(table(rows, ["mode", "size", "median_us", "p99_us", "ratio_p99", "cpu_p50_us", "cpu_p99_us", "rmse",
                       "rmse_frames", "n", "prepare_ms", "peak_mb", "skipped", "note"],
                f"Per-frame solve latency (us), synthetic problems; ratio = p99 / p99 of the prefactored pinv "
                f"product; load average {load:.2f} at start, {os.getloadavg()[0]:.2f} at end"))
    return {"rows": rows, "load_start": load, "load_end": os.getloadavg()[0],
            "data": "benchmarks/synthetic.py: Gaussian-patch bases, 40 moving shapes, 0.3 mm noise"}


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__, modes=""))
