"""Whole takes end to end, as ``livecap solve`` runs them: read the take file, load the actor's
profile (or calibrate and tune on the take, as ``solve`` without ``--profile`` does), stabilise
and fill gaps, build the solver, solve every frame, write the weights CSV.

Takes are generated (livecap.demo.performance.perform: 0.5 mm noise, head motion, bursts of
occlusion) at 0, 5 and 30 % of marker-frames missing, on the bundled demo rig (60 markers x 43
shapes) and on the ICT-FaceKit rig from ../shared/realdata (skipped with the reason when absent),
and written to C3D first. Every mode gets a row: x real time = take seconds / end-to-end seconds,
the stage times beside it, x real time in process CPU seconds (steadier than wall time on a
shared, loaded machine), and the weight RMSE against the generator's ground truth (accuracy
beside speed). The gap-fill column also times the per-gap spline it replaced
(livecap.calibration.gaps_spline) on the same take, as the baseline. ``robust-streamed`` is the
default mode stepped frame by frame (the path before its whole-take one, livecap/modes/robust_take.py):
run right after ``robust`` on the same take, the baseline of that speed-up, with the largest weight
difference between the two printed.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.timing import suite_main, table

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("LIVECAP_SHARED") or ROOT.parent / "shared")
ICT = SHARED / "realdata" / "ict-face"
OCCLUSIONS = (0.0, 0.05, 0.30)
SLOW_MODES = {"lsq"}  # scipy BVLS per frame: timed on the first QUICK_SECONDS of each take only


def _rigs() -> dict:
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.demo.face import demo_rig

    rigs = {"demo": demo_rig(0)}
    if (ICT / "neutral.obj").exists():
        rig = Rig.load(ICT)
        rigs["ict"] = rig, MarkerLayout.load(ICT / "markers.json", rig)
    return rigs


def _take(rig, layout, seconds: float, occlusion: float, folder: Path):
    """A generated take written to C3D, and its ground-truth weights."""
    from livecap.demo.performance import PerformanceSettings, perform
    from transport.takefile import write_take

    perf = perform(rig, layout, PerformanceSettings(seconds=seconds, occlusion=occlusion, seed=5))
    path = folder / f"take_{occlusion:g}.c3d"
    write_take(perf.take, path)
    return path, perf.weights


def _profile(rig, layout, take_path: Path, folder: Path) -> tuple[Path, float]:
    """Calibrate and tune on the take as ``livecap solve`` without ``--profile`` does; save the profile.
    Returns its path and the seconds calibration took (what a user without a saved profile waits for)."""
    from livecap.cli.common import profile_for
    from transport.takefile import read_take

    take = read_take(take_path)
    t0 = time.perf_counter()
    args = argparse.Namespace(profile=None, neutral_seconds=1.0, take=str(take_path), rig="rig")
    profile = profile_for(args, rig, layout, take)
    seconds = time.perf_counter() - t0
    path = folder / "actor.npz"
    profile.save(path)
    return path, seconds


STREAMED = "robust-streamed"  # the robust solver stepped frame by frame: the whole-take path's baseline


class _Stepped:
    """A solver reduced to ``step``/``reset``, so ``solve_take`` steps it frame by frame."""

    def __init__(self, solver) -> None:
        self.step, self.reset = solver.step, solver.reset


def _options(mode: str, profile) -> dict:
    if mode == "rbf":
        from benchmarks.synthetic import rom_keys

        return {"keys": rom_keys(profile)}
    return {}


def solve_end_to_end(mode: str, take_path: Path, profile_path: Path, out: Path, truth: np.ndarray,
                     max_frames: int | None = None) -> dict:
    """One mode over one take file, stage by stage; weight RMSE against ``truth``."""
    from livecap.calibration.profile import Profile
    from livecap.core.take import Take
    from livecap.modes.registry import build_solver
    from livecap.offline.solve import prepare_targets, solve_take
    from transport.takefile import read_take
    from transport.weights_csv import write_weights_csv

    clock = time.perf_counter
    cpu0 = time.process_time()
    t0 = clock()
    take = read_take(take_path)
    if max_frames is not None and take.n_frames > max_frames:
        take = Take(take.labels, take.positions[:max_frames], take.valid[:max_frames], take.rate, take.first_frame)
    t1 = clock()
    profile = Profile.load(profile_path)
    t2 = clock()
    solver = _Stepped(build_solver("robust", profile)) if mode == STREAMED else build_solver(
        mode, profile, _options(mode, profile))
    t3 = clock()
    solved = solve_take(take, profile, solver)
    t4 = clock()
    write_weights_csv(out, solved.names, solved.weights, solved.rate, solved.first_frame)
    t5 = clock()
    cpu = time.process_time() - cpu0
    T = take.n_frames
    t_pre = clock()
    prepare_targets(take, profile)  # stabilise + gap fill alone (inside solve_take above)
    prepare = clock() - t_pre
    total = t5 - t0
    rmse = float(np.sqrt(np.mean((solved.weights - truth[:T]) ** 2)))
    return {"frames": T, "seconds_of_take": T / take.rate, "read_s": t1 - t0, "profile_s": t2 - t1,
            "build_s": t3 - t2, "prepare_s": prepare, "solve_s": solved.solve_seconds,
            "write_s": t5 - t4, "total_s": total, "x_real_time": T / take.rate / total,
            "cpu_s": cpu, "x_real_time_cpu": T / take.rate / max(cpu, 1e-9), "weight_rmse": rmse,
            "weights": solved.weights}


FLOOR = ("import numpy, scipy.sparse, scipy.spatial, ezc3d; from solvers.take_filters import causal_poly_take; "
         "causal_poly_take(numpy.zeros((8, 1)), None, 5)")


def _wall(cmd: list[str], runs: int) -> float:
    """Median wall seconds of ``runs`` fresh processes of ``cmd`` (run from the project root)."""
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
        times.append(time.perf_counter() - t0)
        if done.returncode:
            raise RuntimeError(f"{' '.join(cmd)}: {done.stderr.strip().splitlines()[-1:]}")
    return float(np.median(times))


def solve_process(take_path: Path, rig_path: Path, profile_path: Path, out: Path, seconds_of_take: float,
                  runs: int = 3) -> dict:
    """``livecap solve --profile`` as a user runs it, a fresh process each time (interpreter, imports, numba's
    cache loads, the solve, the CSV), beside the floor any process of this stack pays: the same interpreter
    importing numpy, scipy, ezc3d and making one call of a cached numba kernel. Median wall seconds."""
    cli = _wall([sys.executable, "-m", "livecap", "solve", str(take_path), "--rig", str(rig_path),
                 "--profile", str(profile_path), "--out", str(out)], runs)
    floor = _wall([sys.executable, "-c", FLOOR], runs)
    return {"process_s": cli, "x_real_time_process": seconds_of_take / cli, "floor_s": floor,
            "x_real_time_floor": seconds_of_take / floor}


def gap_fill_baseline(take_path: Path, profile_path: Path) -> dict:
    """The banded fill and the per-gap spline it replaced on the same stabilised take."""
    from livecap.calibration.gaps import fill_gaps
    from livecap.calibration.gaps_spline import fill_gaps_per_gap
    from livecap.calibration.profile import Profile
    from livecap.offline.solve import max_gap_frames, prepare_targets
    from transport.takefile import read_take

    take, profile = read_take(take_path), Profile.load(profile_path)
    sel, _, R, t = prepare_targets(take, profile, max_gap_seconds=0)
    local = np.einsum("tji,tnj->tni", R, sel.positions - t[:, None, :])
    gap = max_gap_frames(profile, take.rate)
    t0 = time.perf_counter()
    a, _ = fill_gaps(local, sel.valid, gap)
    t1 = time.perf_counter()
    b, _ = fill_gaps_per_gap(local, sel.valid, gap)
    t2 = time.perf_counter()
    return {"banded_s": t1 - t0, "per_gap_spline_s": t2 - t1, "speedup": (t2 - t1) / max(t1 - t0, 1e-9),
            "max_difference_mm": float(np.abs(a - b).max())}


def _real_take(name: str, seconds: float, occlusion: float, folder: Path):
    """A take of the ICT rig driven by the real performance ``name`` (benchmarks.realperf: 60 Hz, 0.5 mm noise,
    ``seconds`` from 10 s in, clamped), written to C3D; its ground-truth weights; and the plain profile from its
    separate neutral take (as ``livecap realeval``) with the seconds that calibration took."""
    from benchmarks.realperf import ict_performance
    from livecap.demo.curves_take import CurveTakeSettings
    from transport.llf_csv import read_llf_csv
    from transport.takefile import write_take

    csv = SHARED / "realdata" / "performance" / f"{name}.csv"
    start = max(0.0, min(10.0, read_llf_csv(csv).times[-1] - seconds)) if csv.exists() else 0.0
    _, _, ct, profile, calib_s = ict_performance(name, CurveTakeSettings(start=start, seconds=seconds,
                                                                         occlusion=occlusion))
    path = folder / f"{name}_{occlusion:g}.c3d"
    write_take(ct.take, path)
    profile.save(folder / "actor.npz")
    return path, ct.weights, folder / "actor.npz", calib_s, ct.take.n_frames / ct.take.rate


def run(quick: bool = False, modes: tuple[str, ...] = (), process: bool = True,
        performances: tuple[str, ...] = ()) -> dict:
    """``process``: also time ``livecap solve --profile`` (the default mode) in fresh processes, three per take.
    ``performances``: also takes of the ICT rig driven by these real performances (``realdata/performance``)."""
    from livecap.modes.registry import DEFAULT_MODE, MODES

    seconds = 5.0 if quick else 30.0
    modes = tuple(m for m in modes if m) or (*MODES, STREAMED)
    performances = tuple(p for p in performances if p)
    res: dict = {"take_seconds": seconds,
                 "default_mode": f"{DEFAULT_MODE} (robust: these profiles carry no animation prior)",
                 "load_average": os.getloadavg(),
                 "rigs": {}, "skipped": {}}
    rigs = _rigs()
    if "ict" not in rigs:
        res["skipped"]["ict"] = f"ICT-FaceKit rig not found at {ICT} (../shared/realdata absent)"
        print(f"ict: skipped, {res['skipped']['ict']}")
        if performances:
            raise SystemExit(f"--performances needs the ICT rig: {res['skipped']['ict']}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)

        def takes():
            """(key, rig name, rig, occlusion, take path, truth, profile path, how the profile was made and in how
            many seconds, take seconds) of every take."""
            for rig_name, (rig, layout) in rigs.items():
                for occ in OCCLUSIONS:
                    take_path, truth = _take(rig, layout, seconds, occ, folder)
                    profile_path, calib_s = _profile(rig, layout, take_path, folder)
                    yield f"{rig_name} {rig.n_shapes} shapes, {occ:.0%} occluded", rig_name, rig, occ, take_path, \
                        truth, profile_path, ("calibrate+tune on the take", calib_s), seconds
            for name in performances:
                rig = rigs["ict"][0]
                for occ in OCCLUSIONS:
                    take_path, truth, profile_path, calib_s, take_s = _real_take(name, seconds, occ, folder)
                    yield f"ict {name} (real), {occ:.0%} occluded", "ict", rig, occ, take_path, truth, profile_path, \
                        ("calibrate from its neutral take", calib_s), take_s

        for key, rig_name, rig, occ, take_path, truth, profile_path, (how, calib_s), take_s in takes():
            entry: dict = {"calibrate_and_tune_s": calib_s, "modes": {}}
            weights: dict = {}
            if occ > 0:
                entry["gap_fill"] = gap_fill_baseline(take_path, profile_path)
            if process:
                rig_path = ICT if rig_name == "ict" else folder / "demo_rig.npz"
                if rig_name != "ict" and not rig_path.exists():
                    rig.save(rig_path)
                entry["process"] = p = solve_process(take_path, rig_path, profile_path, folder / "p.csv", take_s)
                print(f"{key}: `livecap solve --profile` process {p['process_s']:.2f} s "
                      f"({p['x_real_time_process']:.1f}x real time); the stack's floor {p['floor_s']:.2f} s "
                      f"({p['x_real_time_floor']:.1f}x)", flush=True)
            for mode in modes:
                limit = int(min(take_s, 5.0) * 120) if mode in SLOW_MODES else None
                r = solve_end_to_end(mode, take_path, profile_path, folder / "w.csv", truth, limit)
                weights[mode] = r.pop("weights")
                entry["modes"][mode] = r
                rows.append({"take": key, "mode": mode, "s of take": r["seconds_of_take"],
                             "x real time": r["x_real_time"], "total s": r["total_s"],
                             "x rt (CPU)": r["x_real_time_cpu"],
                             "read": r["read_s"], "profile": r["profile_s"], "build": r["build_s"],
                             "stabilise+fill": r["prepare_s"], "solve": r["solve_s"], "write": r["write_s"],
                             "RMSE": r["weight_rmse"]})
                print(f"{key:>32} {mode:>16} {r['x_real_time']:8.1f}x real time  RMSE {r['weight_rmse']:.4f}",
                      flush=True)
            res["rigs"][key] = entry
            if "robust" in weights and STREAMED in weights:
                entry["robust_vs_streamed_max_abs"] = float(np.abs(weights["robust"] - weights[STREAMED]).max())
                print(f"{key}: robust whole take vs {STREAMED}: max |weight difference| "
                      f"{entry['robust_vs_streamed_max_abs']:.2e}", flush=True)
            gf = entry.get("gap_fill")
            print(f"{key}: {how} {calib_s:.2f} s"
                  + (f"; gap fill {gf['banded_s']:.3f} s vs per-gap spline {gf['per_gap_spline_s']:.2f} s"
                     if gf else ""), flush=True)
    print(table(rows, ["take", "mode", "s of take", "x real time", "x rt (CPU)", "total s", "read", "profile", "build",
                       "stabilise+fill", "solve", "write", "RMSE"],
                "whole take end to end (profile loaded; seconds per stage)"))
    return res


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__, modes="", performances=""))
