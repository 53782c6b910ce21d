"""The box QP of a git revision against this tree's, A/B in one process (issue 18 item 3, wave 4).

Each mode is built twice on the same synthetic stream (benchmarks/synthetic.py): once with this tree's
``solvers.box_qp.BoxQP`` and once with the class from ``--before`` (default 56fe5c0, main before the
factor's rank-1 deletions and vectorised loops; 118c8ce is main before the box QP kept a Cholesky factor),
on that revision's compiled kernels where it has them, put in ``solvers.qp`` while that solver is built.
The two are timed in alternating blocks, so the machine's load falls on both alike, next to the prefactored
pinv product (the floor) timed in the same blocks. Per row: wall and thread-CPU p50 / p99 (µs),
the weight RMSE against the stream's truth (first 300 frames from a reset solver) and the largest
difference between the two trees' weights over the first 1000 frames (a mode slower than 1 ms a call is
timed on 300 calls):

    python -m benchmarks.box_qp_ab [--quick] [--modes robust,qp] [--sizes 72x150,72x1000] [--before REV]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

import solvers.qp
from benchmarks.solve_latency import SIZES
from benchmarks.synthetic import synthetic_profile, synthetic_stream
from livecap.modes.registry import build_solver


def _git_show(rev: str, path: str) -> str | None:
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=root, capture_output=True, text=True)
    return out.stdout if out.returncode == 0 else None


def old_box_qp(rev: str) -> type:
    """``BoxQP`` as solvers/box_qp.py defines it at git revision ``rev``, on that revision's compiled kernels
    (solvers/box_qp_kernels.py, written to a temporary file so that numba can cache them) where it has them."""
    src = _git_show(rev, "solvers/box_qp.py")
    if src is None:
        raise SystemExit(f"no solvers/box_qp.py at {rev}")
    mod = types.ModuleType(f"box_qp_{rev}")
    kernels = _git_show(rev, "solvers/box_qp_kernels.py")
    if kernels is not None:
        path = Path(tempfile.gettempdir()) / f"box_qp_kernels_{rev}.py"
        if not path.exists() or path.read_text() != kernels:
            path.write_text(kernels)
        spec = importlib.util.spec_from_file_location(path.stem, path)
        mod._kernels = sys.modules[spec.name] = importlib.util.module_from_spec(spec)  # numba's cache imports it
        spec.loader.exec_module(mod._kernels)
        spelled = "from solvers import box_qp_kernels as k"
        if spelled not in src:
            raise RuntimeError(f"{rev}:solvers/box_qp.py does not import its kernels as {spelled!r}: "
                               "its BoxQP would run this tree's kernels")
        src = src.replace(spelled, "k = _kernels")
    exec(compile(src, f"{rev}:solvers/box_qp.py", "exec"), mod.__dict__)
    return mod.BoxQP


COMPARED = 1000  # frames of the stream on which the two trees' weights are compared


def _build(mode: str, profile, box: type, target, valid):
    """The mode's solver, with its workspace for ``valid``'s pattern (made on the first step) on ``box``.

    FrameQP makes a BoxQP for each new visibility pattern through the name ``solvers.qp.BoxQP``, at the
    step that first sees it: whoever steps this solver on a stream with gaps sets that name to ``box``
    first (``compare`` does so at each block), or the later patterns' workspaces get this tree's class.
    """
    keep = solvers.qp.BoxQP
    solvers.qp.BoxQP = box
    try:
        solver = build_solver(mode, profile, {})
        solver.step(target, valid)
        return solver
    finally:
        solvers.qp.BoxQP = keep


def _stats(wall: list, cpu: list) -> dict:
    w, c = np.asarray(wall) / 1e3, np.asarray(cpu) / 1e3
    return {"n": len(w), "p50_us": float(np.median(w)), "p99_us": float(np.percentile(w, 99)),
            "cpu_p50_us": float(np.median(c)), "cpu_p99_us": float(np.percentile(c, 99))}


def compare(mode: str, n: int, m: int, before: type, count: int, block: int = 250) -> dict:
    profile = synthetic_profile(n, m)
    targets, valid, truth = synthetic_stream(profile, 3000)
    T = len(targets)
    flat = targets.reshape(T, -1)
    pinv = np.linalg.pinv(profile.basis)
    boxes = {"before": before, "after": solvers.qp.BoxQP}
    runs = {k: _build(mode, profile, box, targets[0], valid[0]) for k, box in boxes.items()}
    out, t0 = {}, time.perf_counter()
    for name, s in runs.items():  # accuracy and equality from reset solvers, then warm for timing
        s.reset()
        solvers.qp.BoxQP = boxes[name]
        out[name] = np.array([s.step(targets[i], valid[i]) for i in range(COMPARED)])
    if (time.perf_counter() - t0) / (2 * COMPARED) > 1e-3:  # milliseconds a call: fewer timed calls
        count, block = min(count, 300), 50
    diff = float(np.abs(out["before"] - out["after"]).max())
    rmse = {k: float(np.sqrt(np.mean((W[:300] - truth[:300]) ** 2))) for k, W in out.items()}
    calls = {"pinv": lambda i: pinv @ flat[i % T], **{k: (lambda i, s=s: s.step(targets[i % T], valid[i % T]))
                                                      for k, s in runs.items()}}
    samples = {k: ([], []) for k in calls}
    clock, thread = time.perf_counter_ns, time.thread_time_ns
    for r in range(max(1, count // block)):
        order = list(calls) if r % 2 == 0 else list(reversed(calls))
        for k in order:
            fn, (wall, cpu) = calls[k], samples[k]
            solvers.qp.BoxQP = boxes.get(k, boxes["after"])
            start = r * block
            for i in range(start, start + block):
                c0, t0 = thread(), clock()
                fn(i)
                t1, c1 = clock(), thread()
                wall.append(t1 - t0)
                cpu.append(c1 - c0)
    solvers.qp.BoxQP = boxes["after"]
    res = {k: _stats(*v) for k, v in samples.items()}
    for k in runs:
        res[k]["rmse"] = rmse[k]
        res[k]["ratio_p99_pinv"] = res[k]["p99_us"] / res["pinv"]["p99_us"]
    return {"mode": mode, "size": f"{n}x{m}", "max_abs_diff": diff, **res,
            "after/before_p99": res["after"]["p99_us"] / res["before"]["p99_us"],
            "after/before_cpu_p99": res["after"]["cpu_p99_us"] / res["before"]["cpu_p99_us"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="1000 timed calls per solver instead of 6000")
    ap.add_argument("--modes", default="robust,qp")
    ap.add_argument("--sizes", default=",".join(f"{n}x{m}" for n, m in SIZES))
    ap.add_argument("--before", default="56fe5c0")
    ap.add_argument("--json")
    args = ap.parse_args()
    before = old_box_qp(args.before)
    count = 1000 if args.quick else 6000
    rows, load = [], os.getloadavg()
    for size in args.sizes.split(","):
        n, m = (int(v) for v in size.split("x"))
        for mode in args.modes.split(","):
            row = compare(mode, n, m, before, count)
            rows.append(row)
            b, a, p = row["before"], row["after"], row["pinv"]
            print(f"{mode:8s} {row['size']:9s} wall p50/p99 before {b['p50_us']:.0f}/{b['p99_us']:.0f} after "
                  f"{a['p50_us']:.0f}/{a['p99_us']:.0f} (x{row['after/before_p99']:.2f})  CPU before "
                  f"{b['cpu_p50_us']:.0f}/{b['cpu_p99_us']:.0f} after {a['cpu_p50_us']:.0f}/{a['cpu_p99_us']:.0f}"
                  f"  pinv {p['p50_us']:.1f}/{p['p99_us']:.1f}  RMSE {b['rmse']:.6f}/{a['rmse']:.6f}"
                  f"  max|diff| {row['max_abs_diff']:.1e}  load {os.getloadavg()[0]:.2f}", flush=True)
    out = {"before": args.before, "rows": rows, "load_start": load, "load_end": os.getloadavg(),
           "data": "benchmarks/synthetic.py: Gaussian-patch bases, 40 moving shapes, 0.3 mm noise, all markers seen"}
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
        print(f"written {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
