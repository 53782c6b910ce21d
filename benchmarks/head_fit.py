"""The streamed head fit of a git revision against this tree's, A/B in one process (issue 18 item 3, wave 4).

``HeadStabiliser.step`` (default robust settings) from ``--before`` (default b1dfbd9, main before the
prepared single-frame fit; its ``solvers.rigid`` imports resolve to this tree's, which compute the same)
and from this tree, on the same frames: the bundled demo take (``livecap generate`` seed 0, 10 s at
120 Hz, its own calibrated profile) and the same take made hostile (a stable marker jumping 5-20 mm
for a few frames now and then, one missing for a while, fewer than 3 stable
markers so every visible marker fits, none at all so the pose is held), and ``real``: the ICT rig driven
by a real Live Link Face performance (``livecap generate --rig ../shared/realdata/ict-face --curves
../shared/realdata/performance/S07-001.csv``, 4058 frames at 60 Hz, 5 % missing), calibrated on its neutral
take (skipped with the reason when ../shared is absent). The two are timed in
alternating blocks of frames, so the machine's load falls on both alike; thread CPU per call
(``time.thread_time_ns``), p50 / p99 in µs, beside the largest difference of the two trees' poses
(rotation entries, translation mm) and stabilised markers (mm) over every frame:

    python -m benchmarks.head_fit [--quick] [--takes demo,hostile,real] [--before REV] [--json FILE]
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

from benchmarks.timing import machine, table
from livecap.calibration.stabilise import HeadStabiliser

BLOCK = 200  # frames per timed block; the trees take turns block by block
ROOT = Path(__file__).resolve().parents[1]
REALDATA = Path(os.environ.get("LIVECAP_SHARED") or ROOT.parent / "shared") / "realdata"


def old_stabiliser(rev: str) -> type:
    """``HeadStabiliser`` as livecap/calibration/stabilise.py defines it at git revision ``rev``."""
    path = "livecap/calibration/stabilise.py"
    src = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout
    mod = types.ModuleType(f"stabilise_{rev}")
    exec(compile(src, f"{rev}:{path}", "exec"), mod.__dict__)
    return mod.HeadStabiliser


def demo_take():
    """The bundled demo take's labelled frames and its profile's stabiliser settings."""
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
        take = read_take(work / DEMO_TAKE).select(layout.labels)
        profile = calibrate(rig, layout, estimate_neutral(take, layout.stable, 120))
    return np.array(take.positions, np.float64), np.array(take.valid, bool), profile.stabiliser()


def real_take():
    """The ICT rig driven by the S07-001 performance (``livecap generate --curves``), calibrated on its
    neutral take as ``livecap calibrate`` does; None and the reason when ../shared/realdata is absent."""
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from transport.takefile import read_take

    rig_dir, curves = REALDATA / "ict-face", REALDATA / "performance" / "S07-001.csv"
    if not (rig_dir / "neutral.obj").exists() or not curves.exists():
        return None, f"skipped: {rig_dir} or {curves} not found (../shared/realdata is not beside this checkout)"
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "livecap", "generate", "--rig", str(rig_dir), "--curves", str(curves),
                        "--out", tmp], cwd=ROOT, check=True, capture_output=True)
        rig = Rig.load(rig_dir)
        layout = MarkerLayout.load(rig_dir / "markers.json", rig)
        take = read_take(Path(tmp) / "S07-001.c3d").select(layout.labels)
        neutral = read_take(Path(tmp) / "S07-001_neutral.c3d").select(layout.labels)
    profile = calibrate(rig, layout, estimate_neutral(neutral, layout.stable))
    return (np.array(take.positions, np.float64), np.array(take.valid, bool), profile.stabiliser()), ""


def hostile(pos: np.ndarray, valid: np.ndarray, stable: np.ndarray, seed: int = 0):
    """The take with jumping, missing, too few and no markers (NaN), every ~40 frames."""
    rng = np.random.default_rng(seed)
    pos, valid = pos.copy(), valid.copy()
    k = np.flatnonzero(stable)
    for start in range(20, len(pos) - 10, 40):
        kind = (start // 40) % 5
        span = slice(start, start + int(rng.integers(2, 8)))
        if kind in (0, 1):
            v = rng.normal(size=3)
            pos[span, k[rng.integers(len(k))]] += rng.uniform(5.0, 20.0) * v / np.linalg.norm(v)
        elif kind == 2:
            j = k[rng.integers(len(k))]
            valid[span, j] = False
            pos[span, j] = 0.0  # as the decoders deliver it (NaN there made the old step raise in eigh)
        elif kind == 3:
            valid[span, k[1:]] = False
            pos[span, k[1:]] = 0.0
        else:
            valid[span] = False
            pos[span] = np.nan
    return pos, valid


def compare(pos: np.ndarray, valid: np.ndarray, stab: HeadStabiliser, before: type, count: int) -> dict:
    args = (stab.reference, stab.stable, stab.robust, stab.iterations, stab.floor_mm)
    runs = {"before": before(*args), "after": HeadStabiliser(*args)}
    T = len(pos)
    outs = {}
    for name, s in runs.items():
        s.reset()
        outs[name] = [s.step(pos[i], valid[i]) for i in range(T)]
    dR = max(float(np.abs(a[1] - b[1]).max()) for a, b in zip(outs["before"], outs["after"], strict=True))
    dt = max(float(np.abs(a[2] - b[2]).max()) for a, b in zip(outs["before"], outs["after"], strict=True))
    dl = max(float(np.nan_to_num(np.abs(a[0] - b[0]), nan=np.inf).max())
             for a, b in zip(outs["before"], outs["after"], strict=True))
    cpu = {k: [] for k in runs}
    thread = time.thread_time_ns
    for r in range(max(1, count // BLOCK)):
        for k in (list(runs) if r % 2 == 0 else list(reversed(runs))):
            step, samples = runs[k].step, cpu[k]
            for i in range(r * BLOCK, (r + 1) * BLOCK):
                c0 = thread()
                step(pos[i % T], valid[i % T])
                samples.append(thread() - c0)
    res = {k: {"n": len(v), "cpu_p50_us": float(np.median(v)) / 1e3, "cpu_p99_us": float(np.percentile(v, 99)) / 1e3}
           for k, v in cpu.items()}
    return {**{f"{k}_{m}": v[m] for k, v in res.items() for m in ("cpu_p50_us", "cpu_p99_us")},
            "p50 ratio": res["before"]["cpu_p50_us"] / res["after"]["cpu_p50_us"],
            "p99 ratio": res["before"]["cpu_p99_us"] / res["after"]["cpu_p99_us"],
            "max |dR|": dR, "max |dt| mm": dt, "max |d local| mm": dl}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="2400 timed frames per tree and take instead of 12000")
    ap.add_argument("--takes", default="demo,hostile,real")
    ap.add_argument("--before", default="b1dfbd9")
    ap.add_argument("--json")
    args = ap.parse_args()
    before = old_stabiliser(args.before)
    count = 2400 if args.quick else 12000
    pos, valid, stab = demo_take()
    takes = {"demo": (pos, valid, stab), "hostile": (*hostile(pos, valid, stab.stable), stab)}
    if "real" in args.takes.split(","):
        takes["real"], why = real_take()
        if takes["real"] is None:
            print(f"real: {why}")
    load = os.getloadavg()
    rows = []
    for name in args.takes.split(","):
        if takes[name] is not None:
            rows.append({"take": name, **compare(*takes[name], before, count)})
    load_end = os.getloadavg()
    cols = ["take", "before_cpu_p50_us", "after_cpu_p50_us", "p50 ratio", "before_cpu_p99_us", "after_cpu_p99_us",
            "p99 ratio", "max |dR|", "max |dt| mm", "max |d local| mm"]
    title = f"HeadStabiliser.step, {args.before} (before) vs this tree (after), thread CPU µs per frame"
    print(table(rows, cols, title))
    print(f"load average {load[0]:.2f} -> {load_end[0]:.2f}")
    if args.json:
        out = {"machine": machine(), "before": args.before, "timed_frames": count, "load_start": load,
               "load_end": load_end, "rows": rows}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1, default=float))
        print(f"written {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
