"""Streamed cost of the ``kalman`` mode's ``step`` (or another mode's: ``--mode``), whole and per part, on synthetic
and real-performance takes.

Cases: synthetic 72x150 and 72x1000 (benchmarks/synthetic.py, every marker seen) and the ICT rig driven by
the real performances S07-001 and apfel (``livecap.demo.curves_take``: the whole file, 60 Hz, 0.5 mm noise,
5 % occlusion; plain calibration on the neutral take; the animation prior built from the other files, as
``livecap realeval`` does). Every frame is stepped from a fresh solver; thread CPU (time.thread_time_ns)
and wall per call, p50 / p99 after the first ``WARMUP`` frames. ``--parts`` times the parts of a kalman step
(marker filter, held-out strength trial, fit, IMM) by wrapping them, in a second pass.

A/B: ``--ab TREE`` runs this file alternately under ``PYTHONPATH=TREE`` (e.g. an export of the old commit)
and this tree, in fresh processes, ``--rounds`` times, and reports both with their ratio and the largest
weight difference between the two trees' outputs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

WARMUP = 50
ROOT = Path(__file__).resolve().parents[1]
REAL = ("S07-001", "apfel")


def synthetic_case(n: int, m: int, frames: int):
    from benchmarks.synthetic import synthetic_profile, synthetic_stream

    profile = synthetic_profile(n, m)
    targets, valid, _ = synthetic_stream(profile, frames)
    return profile, targets, valid, {}


def real_case(name: str, seconds: float = 0.0):
    from livecap.calibration.animation_prior import build_prior
    from livecap.cli.realeval import _realdata, _rig
    from livecap.demo.curves_take import CurveTakeSettings, curves_take
    from livecap.offline.real_eval import plain_profile
    from livecap.offline.solve import prepare_targets

    rig, layout = _rig("ict")
    files = sorted((_realdata() / "performance").glob("*.csv"))
    f = next(p for p in files if p.stem == name)
    ct = curves_take(rig, layout, f, CurveTakeSettings(seconds=seconds, noise_mm=0.5, occlusion=0.05))
    profile = plain_profile(rig, layout, ct)
    profile.prior = build_prior([o for o in files if o != f], rig.names, rig.lower, rig.upper)
    take, targets, _, _ = prepare_targets(ct.take, profile)
    return profile, targets, take.valid, {"rate": ct.take.rate}


def _build(profile, options, mode: str = "kalman"):
    from livecap.modes.registry import build_solver

    return build_solver(mode, profile, options)


def stream(profile, targets, valid, options, mode: str = "kalman") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weights of every frame from a fresh solver of ``mode``, and each call's thread CPU and wall (µs)."""
    solver = _build(profile, options, mode)
    T = len(targets)
    W = np.empty((T, len(profile.names)))
    cpu, wall = np.empty(T), np.empty(T)
    thread, clock = time.thread_time_ns, time.perf_counter_ns
    for i in range(T):
        c0, t0 = thread(), clock()
        W[i] = solver.step(targets[i], valid[i])
        t1, c1 = clock(), thread()
        cpu[i], wall[i] = (c1 - c0) / 1e3, (t1 - t0) / 1e3
    return W, cpu, wall


def parts(profile, targets, valid, options) -> dict:
    """Thread CPU (µs per frame, p50 / p99 / mean) of each part, by wrapping each part's call."""
    import solvers.tracking as tracking

    solver = _build(profile, options)
    spent: dict[str, float] = {}
    thread = time.thread_time_ns

    def timed(name, fn):
        def call(*a, **k):
            c0 = thread()
            out = fn(*a, **k)
            spent[name] = spent.get(name, 0.0) + (thread() - c0) / 1e3
            return out
        return call

    solver.filter.step = timed("filter", solver.filter.step)
    solver.selector.observe = timed("trial", solver.selector.observe)
    solver.selector.observe_unbounded = timed("trial", solver.selector.observe_unbounded)  # the streamed ICT trial
    for qp in solver._fits.values():
        qp.step = timed("fit", qp.step)
    imm_step = tracking.IMMFilter.step
    tracking.IMMFilter.step = lambda self, w: timed("imm", imm_step)(self, w)
    rows: dict[str, list[float]] = {k: [] for k in ("filter", "trial", "fit", "imm", "total")}
    try:
        for i in range(len(targets)):
            spent.clear()
            c0 = thread()
            solver.step(targets[i], valid[i])
            total = (thread() - c0) / 1e3
            for k in rows:
                rows[k].append(total if k == "total" else spent.get(k, 0.0))
    finally:
        tracking.IMMFilter.step = imm_step
    return {k: _stats(np.array(v[WARMUP:])) for k, v in rows.items()}


def _stats(a: np.ndarray) -> dict:
    return {"p50": float(np.median(a)), "p99": float(np.percentile(a, 99)), "mean": float(a.mean())}


def cases(quick: bool) -> dict:
    out = {"synthetic 72x150": lambda: synthetic_case(72, 150, 600 if quick else 2000),
           "synthetic 72x1000": lambda: synthetic_case(72, 1000, 150 if quick else 400)}
    for name in REAL:
        out[f"ict {name}"] = lambda name=name: real_case(name, 20.0 if quick else 0.0)
    return out


def measure(which: list[str], quick: bool, with_parts: bool, weights: str | None, mode: str = "kalman") -> dict:
    res, saved = {}, {}
    for label, make in cases(quick).items():
        if which and not any(w in label for w in which):
            continue
        profile, targets, valid, options = make()
        W, cpu, wall = stream(profile, targets, valid, options, mode)
        saved[label] = W
        res[label] = {"frames": len(targets), "cpu": _stats(cpu[WARMUP:]), "wall": _stats(wall[WARMUP:])}
        if with_parts:
            res[label]["parts"] = parts(profile, targets, valid, options)
    if weights:
        np.savez(weights, **saved)
    return res


def ab(other: str, rounds: int, argv: list[str]) -> dict:
    """Alternate fresh processes of this file under ``other``'s and this tree's code."""
    runs: dict[str, list[dict]] = {"old": [], "new": []}
    tmp = Path(tempfile.mkdtemp())
    env = {**os.environ, "LIVECAP_SHARED": os.environ.get("LIVECAP_SHARED", str(ROOT.parent / "shared"))}
    for r in range(rounds):
        for tag, tree in (("old", other), ("new", str(ROOT))) if r % 2 == 0 else (("new", str(ROOT)), ("old", other)):
            out = tmp / f"{tag}{r}.json"
            cmd = [sys.executable, __file__, *argv, "--json", str(out), "--weights", str(tmp / f"{tag}.npz")]
            subprocess.run(cmd, check=True, env={**env, "PYTHONPATH": tree})
            runs[tag].append({**json.loads(out.read_text()), "load": os.getloadavg()[0]})
    old, new = np.load(tmp / "old.npz"), np.load(tmp / "new.npz")
    summary = {}
    for label in old.files:
        def best(tag, stat, label=label):
            return min(run["result"][label]["cpu"][stat] for run in runs[tag])
        summary[label] = {"max_abs_dw": float(np.abs(old[label] - new[label]).max()),
                          **{f"cpu_{s}_old_new": [best("old", s), best("new", s)] for s in ("p50", "p99")},
                          "p50_ratio": best("old", "p50") / best("new", "p50"),
                          "p99_ratio": best("old", "p99") / best("new", "p99")}
        print(f"{label}: thread CPU p50 {summary[label]['cpu_p50_old_new'][0]:.0f} -> "
              f"{summary[label]['cpu_p50_old_new'][1]:.0f} µs ({summary[label]['p50_ratio']:.1f}x), p99 "
              f"{summary[label]['cpu_p99_old_new'][0]:.0f} -> {summary[label]['cpu_p99_old_new'][1]:.0f} µs "
              f"({summary[label]['p99_ratio']:.1f}x), max |dw| {summary[label]['max_abs_dw']:.2e}")
    return {"summary": summary, "runs": runs}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="*", default=[], help="substrings of the case labels (default: all)")
    p.add_argument("--quick", action="store_true", help="20 s of each real take, fewer synthetic frames")
    p.add_argument("--mode", default="kalman", help="the mode whose step is timed (default kalman)")
    p.add_argument("--parts", action="store_true", help="also time each part of a step (kalman only)")
    p.add_argument("--ab", help="another tree (its code is 'old'): alternate fresh processes, compare")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--weights", help="save each case's weights (.npz)")
    p.add_argument("--json", help="write the result as JSON")
    a = p.parse_args()
    if a.parts and a.mode != "kalman":
        p.error("--parts times the parts of a kalman step: not with --mode " + a.mode)
    start = {"utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "load": os.getloadavg()}
    if a.ab:
        argv = [*(["--cases", *a.cases] if a.cases else []), *(["--quick"] if a.quick else []),
                *(["--parts"] if a.parts else []), "--mode", a.mode]
        result = ab(a.ab, a.rounds, argv)
    else:
        result = measure(a.cases, a.quick, a.parts, a.weights, a.mode)
        print(json.dumps(result, indent=1))
    out = {"start": start, "end": {"utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "load": os.getloadavg()},
           "result": result}
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
