"""The compiled (numba) kernels against the numpy code of a git revision, A/B in one process (issue 18:
robust p99 at 72x150, offline ICT 5 % / 30 %).

``--parts`` picks what the "before" solver takes from ``--before`` (default 4eeff2c, before the kernels):
``imm``, the IMM weight stage (solvers/tracking.py ``IMMFilter``, same parameters), ``box``, the box QP
(solvers/box_qp.py ``BoxQP``, put in ``solvers.qp`` while that solver builds and steps, so every visibility
pattern's workspace gets it), or both; "after" is this tree.

Per-frame: the ``robust`` mode on benchmarks/synthetic.py streams at solve_latency's sizes, the two solvers
stepped in alternating blocks (the load falls on both alike), wall and thread-CPU p50 / p99 per ``step`` (µs),
with ``imm`` also the IMM step alone on the fitted weights. Offline: generated 30 s ICT takes (as
benchmarks.offline makes them, ../shared/realdata) at 0, 5 and 30 % occlusion, read + ``solve_take`` + write per
variant in alternation, best of ``--repeats``; x real time on wall and on process CPU. Each row has the largest
weight difference between the two:

    python -m benchmarks.numba_ab [--parts imm,box] [--quick] [--sizes 72x150] [--takes 0.05,0.3] [--json PATH]
"""

from __future__ import annotations

import argparse
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
from solvers.tracking import IMMFilter

ROOT = Path(__file__).resolve().parents[1]


def old_class(rev: str, path: str, name: str) -> type:
    """Class ``name`` as file ``path`` defines it at git revision ``rev``."""
    src = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True, capture_output=True, text=True).stdout
    mod = types.ModuleType(f"{Path(path).stem}_{rev}")
    exec(compile(src, f"{rev}:{path}", "exec"), mod.__dict__)
    return getattr(mod, name)


class Variant:
    """What one arm uses: its IMM class (None: this tree's) and its BoxQP class (set while it runs)."""

    def __init__(self, imm: type | None, box: type) -> None:
        self.imm, self.box = imm, box

    def build(self, profile):
        solvers.qp.BoxQP = self.box
        s = build_solver("robust", profile, {})
        if self.imm is not None:
            s.weight_filter = twin(s.weight_filter, self.imm)
        return s

    def __call__(self, fn):
        """``fn`` wrapped to run with this arm's BoxQP in ``solvers.qp`` (new patterns' workspaces take it)."""

        def run(*a):
            solvers.qp.BoxQP = self.box
            return fn(*a)

        return run


def twin(f: IMMFilter, before: type):
    """The same filter (parameters, transition matrix) as ``before``'s class."""
    g = before(f.q[0], f.q[1], f.r, 100.0, f.p_move)
    g.transition = f.transition.copy()
    return g


def _stats(ns: list) -> tuple[float, float]:
    a = np.asarray(ns) / 1e3
    return float(np.median(a)), float(np.percentile(a, 99))


def _alternate(calls: dict, count: int, block: int) -> dict:
    """``calls[k](i)`` in alternating blocks; wall and thread-CPU p50 / p99 (µs) per key."""
    samples = {k: ([], []) for k in calls}
    clock, thread = time.perf_counter_ns, time.thread_time_ns
    for r in range(max(1, count // block)):
        for k in (list(calls) if r % 2 == 0 else list(reversed(calls))):
            fn, (wall, cpu) = calls[k], samples[k]
            for i in range(r * block, (r + 1) * block):
                c0, t0 = thread(), clock()
                fn(i)
                t1, c1 = clock(), thread()
                wall.append(t1 - t0)
                cpu.append(c1 - c0)
    return {k: dict(zip(("p50_us", "p99_us", "cpu_p50_us", "cpu_p99_us"), (*_stats(w), *_stats(c)), strict=True))
            for k, (w, c) in samples.items()}


def per_frame(n: int, m: int, arms: dict, count: int, block: int = 250) -> dict:
    profile = synthetic_profile(n, m)
    targets, valid, truth = synthetic_stream(profile, 3000)
    T = len(targets)
    runs = {k: arm.build(profile) for k, arm in arms.items()}
    out = {}
    for k, s in runs.items():
        s.reset()
        out[k] = np.array([arms[k](s.step)(targets[i], valid[i]) for i in range(1000)])
    calls = {k: arms[k](lambda i, s=s: s.step(targets[i % T], valid[i % T])) for k, s in runs.items()}
    if arms["before"].imm is not None:  # the IMM step alone on the fitted weights
        W = np.array([runs["after"].inner.step(targets[i], valid[i]) for i in range(T)])
        imms = {"imm before": twin(runs["after"].weight_filter, arms["before"].imm),
                "imm after": runs["after"].weight_filter}
        for f in imms.values():
            f.reset()
            f.step(W[0])
        calls.update({k: (lambda i, f=f: f.step(W[i % T])) for k, f in imms.items()})
    res = _alternate(calls, count, block)
    return {"size": f"{n}x{m}", "max_abs_diff": float(np.abs(out["before"] - out["after"]).max()),
            "rmse": float(np.sqrt(np.mean((out["after"][:300] - truth[:300]) ** 2))), **res}


def offline(occlusion: float, arms: dict, repeats: int, folder: Path) -> dict | None:
    from benchmarks.offline import ICT, _profile, _rigs, _take
    from livecap.calibration.profile import Profile
    from livecap.offline.solve import solve_take
    from transport.takefile import read_take
    from transport.weights_csv import write_weights_csv

    if "ict" not in _rigs():
        print(f"offline: skipped, no ICT rig at {ICT}")
        return None
    rig, layout = _rigs()["ict"]
    take_path, truth = _take(rig, layout, 30.0, occlusion, folder)
    profile_path, _ = _profile(rig, layout, take_path, folder)
    best = {}
    weights = {}
    for r in range(repeats):
        for k in (("before", "after") if r % 2 == 0 else ("after", "before")):
            cpu0, t0 = time.process_time(), time.perf_counter()
            take = read_take(take_path)
            profile = Profile.load(profile_path)
            solver = arms[k].build(profile)
            t1 = time.perf_counter()
            solved = arms[k](solve_take)(take, profile, solver)
            t2 = time.perf_counter()
            write_weights_csv(folder / f"{k}.csv", solved.names, solved.weights, solved.rate, solved.first_frame)
            t3, cpu = time.perf_counter(), time.process_time() - cpu0
            row = {"total_s": t3 - t0, "cpu_s": cpu, "solve_take_s": t2 - t1, "solve_s": solved.solve_seconds}
            best[k] = {key: min(v, best.get(k, row)[key]) for key, v in row.items()}
            weights[k] = solved.weights
    seconds = take.n_frames / take.rate
    for row in best.values():
        row["x_real_time"] = seconds / row["total_s"]
        row["x_real_time_cpu"] = seconds / row["cpu_s"]
    rmse = float(np.sqrt(np.mean((weights["after"] - truth[:take.n_frames]) ** 2)))
    return {"take": f"ICT {occlusion:.0%}", "frames": take.n_frames, "rmse": rmse,
            "max_abs_diff": float(np.abs(weights["before"] - weights["after"]).max()), **best}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="1000 timed calls per variant instead of 6000")
    ap.add_argument("--sizes", default=",".join(f"{n}x{m}" for n, m in SIZES))
    ap.add_argument("--takes", default="0,0.05,0.3", help="ICT take occlusions ('' for none)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--before", default="4eeff2c")
    ap.add_argument("--parts", default="imm,box", help="what 'before' takes from --before: imm, box or both")
    ap.add_argument("--json")
    args = ap.parse_args()
    parts = set(filter(None, args.parts.split(",")))
    after_box = solvers.qp.BoxQP
    arms = {"before": Variant(old_class(args.before, "solvers/tracking.py", "IMMFilter") if "imm" in parts else None,
                              old_class(args.before, "solvers/box_qp.py", "BoxQP") if "box" in parts else after_box),
            "after": Variant(None, after_box)}
    count = 1000 if args.quick else 6000
    out = {"before": args.before, "parts": sorted(parts), "load_start": os.getloadavg(), "per_frame": [],
           "offline": []}
    for size in filter(None, args.sizes.split(",")):
        n, m = (int(v) for v in size.split("x"))
        row = per_frame(n, m, arms, count)
        out["per_frame"].append(row)
        print(f"robust {row['size']:9s} " + "  ".join(
            f"{k} {row[k]['p50_us']:.1f}/{row[k]['p99_us']:.1f} (CPU {row[k]['cpu_p50_us']:.1f}/"
            f"{row[k]['cpu_p99_us']:.1f})" for k in ("before", "after", "imm before", "imm after") if k in row)
            + f"  max|diff| {row['max_abs_diff']:.1e}  load {os.getloadavg()[0]:.2f}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for occ in (float(v) for v in filter(None, args.takes.split(","))):
            row = offline(occ, arms, args.repeats, Path(tmp))
            if row is None:
                break
            out["offline"].append(row)
            print(f"{row['take']:8s} " + "  ".join(
                f"{k} {row[k]['x_real_time']:.1f}x (CPU {row[k]['x_real_time_cpu']:.1f}x) solve_take "
                f"{row[k]['solve_take_s']:.3f} s" for k in ("before", "after"))
                + f"  max|diff| {row['max_abs_diff']:.1e}  load {os.getloadavg()[0]:.2f}", flush=True)
    out["load_end"] = os.getloadavg()
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
        print(f"written {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
