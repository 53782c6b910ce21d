"""Issue 39's ``kalman`` figures, each beside ``robust`` measured in the same process and run.

* streamed: every frame of the ICT rig driven by the real performances S07-001 and apfel (as
  ``benchmarks.kalman_step``: 0.5 mm, 5 % occlusion, the prior from the other files), thread CPU per ``step``
  p50 / p99 / mean after 50 frames, for robust, kalman, and kalman with its held-out strength trial switched
  off (not a mode: the floor the rest of its step sets);
* paced (``--only paced``, not in a default run): the same, each frame handed over at its time in the take's
  60 Hz stream as ``livecap run`` receives it, so the prior check's thread works between frames (unpaced, the
  benchmark steps ~200x faster than real time and the frame thread waits for every check at its swap);
* 72x1000: the synthetic rig of ``benchmarks.synthetic`` (every marker seen, a ridge), robust, kalman and kalman
  without its trial (``--only 72x1000`` runs it alone; kalman's fit there is solved in marker space,
  solvers/marker_space_qp.py; ``--pace 60`` feeds it as a 60 Hz source would);
* offline: ``solve_take`` of the first 30 s of each performance (with the prior), x real time (wall);
* marker-space primitives at 72x1000 (:func:`marker_space`): why a factorisation that survives visibility changes
  belongs in the 216-dim marker space;
* numba cold / warm: a fresh process compiling kalman's and robust's kernels into an empty ``NUMBA_CACHE_DIR``,
  then a second process loading them (seconds to build both solvers, step 5 frames and solve 120 offline);
* offline, also: the CPU x real time beside the wall, and where kalman's CPU goes (:func:`offline_parts`, stage by
  stage).

``--weights OUT`` saves kalman's streamed weights per case; ``--compare IN`` reports the largest difference from
weights saved so by another tree (the baseline: ``PYTHONPATH=<old tree> python <old tree>/benchmarks/kalman_step.py
--weights`` saves the same cases under the same labels).
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

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # as livecap/__init__.py sets for the
    os.environ.setdefault(_var, "1")  # app: numpy loads here first, and a threaded BLAS makes 216 x 216 factors slow

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a file: PYTHONPATH's packages first (an A/B runs another tree), then ours
    sys.path.append(str(ROOT))

from benchmarks.kalman_step import REAL, WARMUP, _build, _stats, real_case, synthetic_case  # noqa: E402


def _stream(solver, targets, valid, pace_hz: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weights, thread CPU and wall (µs) of every ``step``; with ``pace_hz`` each frame is handed over at its time
    in a stream of that rate, as a live source delivers it (the prior check's thread then runs between frames, as it
    does live, instead of the frame thread waiting for it at a swap)."""
    W = []
    cpu, wall = np.empty(len(targets)), np.empty(len(targets))
    thread, clock = time.thread_time_ns, time.perf_counter_ns
    start = clock()
    for i in range(len(targets)):
        if pace_hz > 0:
            late = (clock() - start) / 1e9 - i / pace_hz
            if late < 0:
                time.sleep(-late)
        c0, t0 = thread(), clock()
        W.append(solver.step(targets[i], valid[i]))
        t1, c1 = clock(), thread()
        cpu[i], wall[i] = (c1 - c0) / 1e3, (t1 - t0) / 1e3
    return np.array(W), cpu, wall


def streamed(profile, targets, valid, options, floor: bool = True, pace_hz: float = 0.0) -> tuple[dict, np.ndarray]:
    """robust, kalman (and kalman without its strength trial) over the same frames, thread CPU (µs; wall beside)
    and the ratios to robust; kalman's weights. ``pace_hz``: frames handed over at that rate (:func:`_stream`)."""
    out, weights = {}, None
    for label in ("robust", "kalman", "kalman, no strength trial") if floor else ("robust", "kalman"):
        solver = _build(profile, options, label.split(",")[0])
        if label.endswith("trial"):
            solver._trial = lambda *a, **k: None  # on the solver: a widened prior replaces its selector
        W, cpu, wall = _stream(solver, targets, valid, pace_hz)
        out[label] = {**_stats(cpu[WARMUP:]), "wall": _stats(wall[WARMUP:])}
        if label == "kalman":
            weights = W
    for label in list(out):
        if label != "robust":
            out[f"{label} / robust"] = {k: out[label][k] / out["robust"][k] for k in ("p50", "p99", "mean")}
    return out, weights


def frame_profile(profile, targets, valid, options, top: float = 1.0, raw: dict | None = None) -> dict:
    """kalman's streamed step with each part wrapped in a thread-CPU clock, frame by frame (issue 39 item 1: what
    the p99 frames contain): per part its p50 / p99 / mean over all frames after WARMUP and its mean and share of
    frames (where it ran) among the slowest ``top`` %; and how often the slowest frames carry a fit on a new
    visibility pattern, a next pattern's workspace, a trial, a prior check's start or swap."""
    import threading

    from solvers.prior_strength import HeldOutStrength
    from solvers.qp import FrameQP
    from solvers.tracking import RotatedIMM

    solver = _build(profile, options, "kalman")
    thread = time.thread_time_ns
    spent: dict[str, float] = {}
    flags: dict[str, bool] = {}

    main = threading.get_ident()  # the prior check's thread builds fits too: not clocked

    def clocked(label, fn):
        def run(*a, **k):
            if threading.get_ident() != main:
                return fn(*a, **k)
            c0 = thread()
            try:
                return fn(*a, **k)
            finally:
                spent[label] = spent.get(label, 0.0) + (thread() - c0) / 1e3
        return run

    def fit_step(self, x, ok, _step=FrameQP.step):
        if threading.get_ident() != main:
            return _step(self, x, ok)
        flags["new fit pattern"] = flags.get("new fit pattern", False) or not self.knows(ok)
        flags["fit restart"] = np.asarray(ok, bool).tobytes() != self._last_key  # another pattern (or fit) than last
        label = "fit, new pattern" if flags["new fit pattern"] else "fit, known pattern"
        return clocked(label, _step)(self, x, ok)

    def use_support(*a, _use=solver._use_support, **k):
        flags["prior swap"] = True
        return _use(*a, **k)

    saved = [(FrameQP, "step", FrameQP.step), (FrameQP, "prepare", FrameQP.prepare),
             (HeldOutStrength, "observe_unbounded", HeldOutStrength.observe_unbounded),
             (HeldOutStrength, "observe", HeldOutStrength.observe), (RotatedIMM, "step", RotatedIMM.step),
             (RotatedIMM, "along", RotatedIMM.along), (RotatedIMM, "set_noise", RotatedIMM.set_noise)]
    FrameQP.step = fit_step
    FrameQP.prepare = clocked("next pattern's workspace", FrameQP.prepare)
    HeldOutStrength.observe_unbounded = clocked("strength trial", HeldOutStrength.observe_unbounded)
    HeldOutStrength.observe = clocked("strength trial", HeldOutStrength.observe)
    RotatedIMM.step = clocked("weight IMM", RotatedIMM.step)
    RotatedIMM.along = clocked("IMM noise (along, set)", RotatedIMM.along)
    RotatedIMM.set_noise = clocked("IMM noise (along, set)", RotatedIMM.set_noise)
    solver.filter.step = clocked("marker filter", solver.filter.step)
    solver._stream_support = clocked("prior check (frames, start, swap)", solver._stream_support)
    if hasattr(solver, "_swap"):  # the swap, at the start of the frame its prior is due on (older trees: elsewhere)
        solver._swap = clocked("prior check (frames, start, swap)", solver._swap)
    solver._use_support = use_support
    labels = ["marker filter", "prior check (frames, start, swap)", "fit, known pattern", "fit, new pattern",
              "next pattern's workspace", "strength trial", "weight IMM", "IMM noise (along, set)"]
    kinds = ["new fit pattern", "next pattern's workspace", "strength trial", "prior check start", "prior swap",
             "fit restart", "strength changed", "after a prior swap"]
    T = len(targets)
    cost = {k: np.zeros(T) for k in [*labels, "rest", "total"]}
    has = {k: np.zeros(T, bool) for k in kinds}
    try:
        for i in range(T):
            spent.clear()
            flags.clear()
            checking, fitted = solver._checking, solver._fit_k
            c0 = thread()
            solver.step(targets[i], valid[i])
            total = (thread() - c0) / 1e3
            for k in labels:
                cost[k][i] = spent.get(k, 0.0)
            cost["total"][i] = total
            cost["rest"][i] = total - sum(spent.get(k, 0.0) for k in labels)
            has["new fit pattern"][i] = flags.get("new fit pattern", False)
            has["next pattern's workspace"][i] = "next pattern's workspace" in spent
            has["strength trial"][i] = "strength trial" in spent
            has["prior check start"][i] = checking is None and solver._checking is not None
            has["prior swap"][i] = flags.get("prior swap", False)
            has["fit restart"][i] = flags.get("fit restart", False)
            has["strength changed"][i] = fitted is not None and solver._fit_k != fitted
            has["after a prior swap"][i] = i > 0 and has["prior swap"][i - 1]
    finally:
        for owner, attr, fn in saved:
            setattr(owner, attr, fn)
    if raw is not None:
        raw.update(cost=cost, has=has)
    total = cost["total"][WARMUP:]
    worst = np.argsort(-total)[:max(1, int(round(len(total) * top / 100)))] + WARMUP
    check = (has["prior check start"] | has["prior swap"] | has["after a prior swap"])[WARMUP:]
    return {"frames": T, "top_percent": top, "top_frames": len(worst), "top_min_us": float(cost["total"][worst].min()),
            # the prior check's frames (its start, its swap, the frame after) left out: what the rest of the step sets
            "p99_without_check_frames": float(np.percentile(total[~check], 99)) if (~check).any() else None,
            "fit_p50_us_on": {k: float(np.median(cost["fit, known pattern"][WARMUP:][v[WARMUP:]]
                                                 + cost["fit, new pattern"][WARMUP:][v[WARMUP:]]))
                              for k, v in has.items() if v[WARMUP:].any()},
            "parts": {k: {**_stats(v[WARMUP:]), "top_mean": float(v[worst].mean()),
                          "top_share_ran": float(np.mean(v[worst] > 0))} for k, v in cost.items()},
            "frames_with": {k: {"all": float(v[WARMUP:].mean()), "top": float(v[worst].mean()),
                                "p50_us_with": float(np.median(total[v[WARMUP:]])) if v[WARMUP:].any() else None,
                                "p50_us_without": float(np.median(total[~v[WARMUP:]]))}
                            for k, v in has.items()},
            "top_frames_list": [int(i) for i in np.sort(worst)]}


def offline(name: str, seconds: float) -> dict:
    """Wall and process CPU seconds (the machine is shared: CPU is the steadier) and x real time of ``solve_take``
    over the first ``seconds`` of performance ``name``."""
    from benchmarks.realperf import ict_performance
    from livecap.calibration.animation_prior import build_prior
    from livecap.cli.realeval import _realdata
    from livecap.demo.curves_take import CurveTakeSettings
    from livecap.modes.registry import build_solver
    from livecap.offline.solve import solve_take

    rig, _, ct, profile, _ = ict_performance(name, CurveTakeSettings(seconds=seconds, noise_mm=0.5, occlusion=0.05))
    others = [p for p in sorted((_realdata() / "performance").glob("*.csv")) if p.stem != name]
    profile.prior = build_prior(others, rig.names, rig.lower, rig.upper)
    take = ct.take
    res = {}
    for mode in ("robust", "kalman"):
        solver = build_solver(mode, profile, {"rate": take.rate})
        solve_take(take, profile, solver)  # once for the workspaces and the kernels' first dispatch
        solver = build_solver(mode, profile, {"rate": take.rate})
        t0, c0 = time.perf_counter(), time.process_time()
        solve_take(take, profile, solver)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        res[mode] = {"seconds": wall, "x_real_time": take.n_frames / take.rate / wall, "cpu_seconds": cpu,
                     "x_real_time_cpu": take.n_frames / take.rate / cpu}
    res["frames"], res["rate"] = take.n_frames, take.rate
    res["kalman parts, CPU s"] = offline_parts(take, profile)
    return res


PARTS = {"targets (stabilise, fill)": ("livecap.offline.solve", "prepare_targets"),
         "marker smoother": ("livecap.modes.marker_kalman", "smooth_take"),
         "prior support check": ("livecap.modes.marker_kalman", "widen_prior"),
         "checked prior swapped in": ("livecap.modes.marker_kalman", "MarkerKalmanSolver._use_support"),
         "held-out strength trials": ("solvers.prior_strength", "HeldOutStrength.observe"),
         "strength in closed form": ("livecap.modes.marker_kalman", "take_strength"),
         "evidence pick": ("livecap.modes.marker_kalman", "MarkerKalmanSolver._evidence_pick"),
         "fit": ("solvers.qp", "FrameQP.step_take"),
         "rigid pose undone": ("solvers.pose_refine", "RigidColumns.remove"),
         "weight IMM": ("solvers.tracking", "IMMFilter.filter")}


def offline_parts(take, profile) -> dict:
    """kalman's ``solve_take`` (one more warm run) with each stage's function wrapped in a process-time clock: CPU
    seconds per stage (not cProfile: its per-call cost swamped the trials, ~2 calls a frame, two thirds of
    its total on a 30 s take where they are about a third), and per call (``"calls"``: a stage run once a pose pass
    is one number per pass; the weight IMM's are forwards, backwards). ``"rest"``: the whole less the stages."""
    import importlib

    from livecap.modes.registry import build_solver
    from livecap.offline.solve import solve_take

    calls: dict[str, list[float]] = {label: [] for label in PARTS}
    saved = []

    def clocked(label, fn):
        def run(*a, **k):
            c0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                calls[label].append(time.process_time() - c0)
        return run

    for label, (module, name) in PARTS.items():
        owner = importlib.import_module(module)
        *cls, attr = name.split(".")
        if cls:
            owner = getattr(owner, cls[0])
        saved.append((owner, attr, owner.__dict__[attr]))
        setattr(owner, attr, clocked(label, getattr(owner, attr)))
    try:
        solver = build_solver("kalman", profile, {"rate": take.rate})
        c0 = time.process_time()
        solve_take(take, profile, solver)
        total = time.process_time() - c0
    finally:
        for owner, attr, fn in saved:
            setattr(owner, attr, fn)
    spent = {label: float(sum(v)) for label, v in calls.items()}
    spent["rest"] = total - sum(spent.values())
    spent["total"] = total
    spent["calls"] = {label: v for label, v in calls.items() if len(v) > 1}
    return spent


COLD = """
import time
t0 = time.perf_counter()
from benchmarks.synthetic import synthetic_profile, synthetic_stream
from livecap.modes.registry import build_solver
p = synthetic_profile(20, 12)
S, V, _ = synthetic_stream(p, 120)
t1 = time.perf_counter()
for mode in ("robust", "kalman"):
    s = build_solver(mode, p, {})
    for i in range(5):
        s.step(S[i], V[i])
    s = build_solver(mode, p, {})
    if hasattr(s, "solve"):
        s.solve(S, V)
print(time.perf_counter() - t1)
"""


def numba_cold_warm() -> dict:
    """Seconds of the same work in a fresh process with an empty numba cache, then in another loading it."""
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": os.pathsep.join(
            [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
        runs = []
        for _ in range(2):
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, "-c", COLD], env=env, capture_output=True, text=True, check=True)
            runs.append({"solvers_s": float(r.stdout.split()[-1]), "process_s": time.perf_counter() - t0})
        files = sorted(p.name.split("-")[0] for p in Path(cache).rglob("*.nbi"))
    return {"cold": runs[0], "warm": runs[1], "cached_kernels": files}


def marker_space(free: int = 530, rows: int = 216, m: int = 1006, reps: int = 20) -> dict:
    """Median µs of the dense primitives a 72x1000 frame could be built from, at kalman's measured ~530 free
    weights: the free block's Cholesky in weight space (what a new pattern or free set costs the box QP today),
    a fresh marker-space factor (J_F J_F' + a I, 216 x 216: Woodbury), one solve with a kept marker-space factor
    (two triangular solves and J_F products), and the gradient of every weight (J' J x)."""
    import scipy.linalg as sl

    rng = np.random.default_rng(0)
    J = rng.normal(0, 1, (rows, m))
    JF = np.ascontiguousarray(J[:, :free])
    HF = JF.T @ JF + 0.1 * np.eye(free)
    S = JF @ JF.T + 0.1 * np.eye(rows)
    Ls = np.linalg.cholesky(S)
    r, x = rng.normal(0, 1, free), rng.normal(0, 1, m)

    def weight_chol():
        np.linalg.cholesky(HF)

    def marker_factor():
        np.linalg.cholesky(JF @ JF.T + 0.1 * np.eye(rows))

    def marker_solve():
        u = sl.solve_triangular(Ls, JF @ r, lower=True, check_finite=False)
        return (r - JF.T @ sl.solve_triangular(Ls.T, u, lower=False, check_finite=False)) / 0.1

    def gradient():
        return J.T @ (J @ x)

    from scipy.linalg.blas import dsyrk
    from scipy.linalg.lapack import dpotrf

    Sf = np.asfortranarray(S)
    W66 = np.asfortranarray(J[:, free:free + 66])

    def marker_refactor():  # what a pass of solvers.marker_space_qp pays where > WOODBURY columns changed sides
        dpotrf(dsyrk(1.0, W66, beta=1.0, c=Sf.copy(order="F"), lower=1, overwrite_c=1), lower=1, clean=0)

    out = {}
    for name, fn in (("weight-space Cholesky of H_FF", weight_chol), ("marker-space factor, fresh", marker_factor),
                     ("marker-space solve, kept factor", marker_solve), ("gradient J'Jx, all weights", gradient),
                     ("marker-space refactor, 66 columns changed (dsyrk + dpotrf)", marker_refactor)):
        t = []
        for _ in range(reps):
            c0 = time.perf_counter_ns()  # wall: BLAS may use both cores
            fn()
            t.append((time.perf_counter_ns() - c0) / 1e3)
        out[name] = float(np.median(t))
    return {"free": free, "rows": rows, "shapes": m, "median_us": out}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="20 s of each real take, 60 frames at 72x1000")
    parts = ["streamed", "paced", "72x1000", "offline", "numba", "marker-space", "profile"]
    p.add_argument("--skip", nargs="*", default=[], choices=parts)
    p.add_argument("--only", nargs="*", default=[], choices=parts, help="run these parts alone (e.g. 72x1000)")
    p.add_argument("--frames", type=int, default=400, help="frames of the 72x1000 take (default 400)")
    p.add_argument("--pace", type=float, default=0.0, metavar="HZ",
                   help="72x1000: each frame handed over at its time in a stream of this rate (as paced, below)")
    p.add_argument("--weights", help="save kalman's streamed weights per case (.npz)")
    p.add_argument("--compare", help="weights saved by another tree: report the largest difference")
    p.add_argument("--json", help="write the result as JSON")
    a = p.parse_args()
    if a.only:
        a.skip = [part for part in parts if part not in a.only]
    start = {"utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "load": os.getloadavg()}
    res: dict = {}
    saved = {}
    if "streamed" not in a.skip:
        for name in REAL:
            label = f"ict {name}"
            res[label], saved[label] = streamed(*real_case(name, 20.0 if a.quick else 0.0))
    if "paced" in a.only:  # not in a default run: it takes the takes' own duration
        for name in REAL:
            case = real_case(name, 20.0 if a.quick else 0.0)
            res[f"ict {name}, paced"] = {**streamed(*case, floor=False, pace_hz=case[3]["rate"])[0],
                                         "rate_hz": case[3]["rate"]}
    if "profile" in a.only:  # not in a default run: it wraps the solver's parts
        for name in REAL:
            res[f"profile ict {name}"] = frame_profile(*real_case(name, 20.0 if a.quick else 0.0))
    if "72x1000" not in a.skip:
        res["synthetic 72x1000"], saved["synthetic 72x1000"] = streamed(
            *synthetic_case(72, 1000, 60 + WARMUP if a.quick else a.frames), pace_hz=a.pace)
        res["synthetic 72x1000"]["pace_hz"] = a.pace
    if "offline" not in a.skip:
        res["offline 30 s"] = {name: offline(name, 30.0) for name in REAL}
    if "marker-space" not in a.skip:
        res["marker-space primitives"] = marker_space()
    if "numba" not in a.skip:
        res["numba"] = numba_cold_warm()
    if a.weights:
        np.savez(a.weights, **saved)
    if a.compare:
        old = np.load(a.compare)
        res["max_abs_dw"] = {k: float(np.abs(old[k] - saved[k]).max()) for k in saved if k in old.files
                             and old[k].shape == saved[k].shape}
    out = {"start": start, "end": {"utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
                                   "load": os.getloadavg()}, "result": res}
    print(json.dumps(out, indent=1))
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
