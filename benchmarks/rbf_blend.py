"""Per-frame cost of the example-based RBF mode (Pyun et al. 2003 §4): p = F d, weights, blend.

Keys: one per shape (a ROM's peak frames) plus the neutral, so M = shapes + 1 keys over 3n
marker coordinates; frames from the same synthetic takes as the QP benchmark. Times are for
``KeyBlendSolver.step`` (input checks included) with all markers seen and with one missing.

Run: ``python -m benchmarks.rbf_blend [--quick] [--json out.json]``.
"""

from __future__ import annotations

import os
import platform
import sys
import time

import numpy as np

from benchmarks.synthetic import frame_problems
from benchmarks.timing import suite_main
from solvers.rbf import KeyBlendSolver

SIZES = [(54, 50), (72, 150)]


def run(quick: bool = False) -> dict:
    frames = 500 if quick else 5000
    out: dict = {"machine": f"{platform.machine()} {platform.python_implementation()} {platform.python_version()}, "
                            f"{os.cpu_count()} cpus, load {os.getloadavg()[0]:.1f}", "frames": frames, "sizes": {}}
    for n, m in SIZES:
        B, S, _ = frame_problems(n, m, frames, seed=n + m)
        t0 = time.perf_counter()
        solver = KeyBlendSolver(np.eye(m) @ B.T, np.eye(m), np.zeros(m), np.ones(m))
        prep = time.perf_counter() - t0
        row = {"keys": m + 1, "features": int(solver.blend.F.shape[0]), "prepare_ms": prep * 1e3}
        for label, missing in (("all seen", None), ("one missing", 5)):
            valid = np.ones(n, bool)
            if missing is not None:
                valid[missing] = False
            solver.step(S[0].reshape(n, 3), valid)  # pattern cache warm
            times = np.empty(frames)
            for i, s in enumerate(S):
                t = time.perf_counter_ns()
                solver.step(s.reshape(n, 3), valid)
                times[i] = (time.perf_counter_ns() - t) / 1e3
            row[label] = {"p50_us": float(np.percentile(times, 50)), "p99_us": float(np.percentile(times, 99))}
        out["sizes"][f"{n}x{m}"] = row
    print_table(out)
    return out


def print_table(r: dict) -> None:
    print(f"RBF per-frame step, {r['frames']} frames, on {r['machine']}")
    print(f"  {'size':8s} {'keys':>5s} {'feat':>5s} {'prep ms':>8s} {'p50 us':>8s} {'p99 us':>8s} "
          f"{'p50 us (1 missing)':>19s} {'p99 us':>8s}")
    for size, row in r["sizes"].items():
        a, b = row["all seen"], row["one missing"]
        print(f"  {size:8s} {row['keys']:5d} {row['features']:5d} {row['prepare_ms']:8.1f} {a['p50_us']:8.1f} "
              f"{a['p99_us']:8.1f} {b['p50_us']:19.1f} {b['p99_us']:8.1f}")


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__))
