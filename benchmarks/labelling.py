"""Labelling unlabelled marker clouds (solvers/labelling.py): right labels, swap length and the
solve's weight RMSE against the labelled solve, on the bundled demo take and on an ICT-FaceKit
take (labels stripped, points shuffled every frame, 2 ghosts per frame, occlusion bursts to 5 %),
each also as a 20 % faster and larger performance than the calibration; the per-frame labelling
CPU time beside the robust solve's step (the baseline, interleaved frame by frame in the same run).

    python -m benchmarks.labelling [--quick] [--against REV]

``--against REV``: also times ``solvers/labelling.py`` as it was at git revision REV (e.g. the
previous labeller), interleaved with the current one on the same frames.

``run(quick)`` prints a table and returns the figures as a dict (``--json FILE`` writes them).
"""

from __future__ import annotations

import sys
from pathlib import Path

from benchmarks.demo_take import TAKE, demo_take
from benchmarks.timing import suite_main, table

ICT = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "ict-face"


def _ict():
    import os

    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.cli.common import tune_on_take
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.demo.performance import perform

    root = Path(os.environ["LIVECAP_SHARED"]) / "realdata" / "ict-face" if os.environ.get("LIVECAP_SHARED") else ICT
    if not (root / "neutral.obj").exists():
        return None
    rig = Rig.load(root)
    layout = MarkerLayout.load(root / "markers.json", rig)
    perf = perform(rig, layout)
    take = perf.take
    profile = calibrate(rig, layout, estimate_neutral(take, layout.stable, int(take.rate)))
    tune_on_take(profile, take)
    return rig, layout, profile, take, perf.weights


def cases(quick: bool):
    """(name, profile, take, truth) for the demo and ICT rigs, normal and 20 % faster/larger."""
    from livecap.demo import truth_path
    from livecap.demo.face import demo_rig
    from livecap.demo.performance import GroundTruth
    from livecap.demo.unlabelled import faster_larger
    from transport.takefile import read_take

    seconds = 6.0 if quick else 20.0
    d = demo_take()
    take = read_take(TAKE)
    T = int(seconds * take.rate)
    out = [("demo", d.profile, take.slice(0, T), GroundTruth.load(truth_path(TAKE)).weights[:T])]
    rig, layout = demo_rig(0)
    fast, W = faster_larger(rig, layout, seconds=seconds)
    out.append(("demo 1.2x faster/larger", d.profile, fast, W))
    ict = _ict()
    if ict is not None:
        rig, layout, profile, take, truth = ict
        out.append(("ICT", profile, take.slice(0, T), truth[:T]))
        fast, W = faster_larger(rig, layout, seconds=seconds)
        out.append(("ICT 1.2x faster/larger", profile, fast, W))
        real = _ict_real(seconds)
        if real is not None:
            out.append(real)
    else:
        print("ICT rig not found: ICT cases skipped", file=sys.stderr)
    return out


def _ict_real(seconds: float):
    """An ICT take driven by a real Live Link Face performance (``livecap generate --curves``: unseen actor,
    head motion, 0.5 mm noise, 5 % occlusion), calibrated on its own neutral take."""
    import os
    import tempfile

    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.cli import main as livecap
    from livecap.cli.common import tune_on_take
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.demo.performance import GroundTruth
    from transport.takefile import read_take

    shared = Path(os.environ["LIVECAP_SHARED"]) / "realdata" if os.environ.get("LIVECAP_SHARED") else ICT.parent
    csv = shared / "performance" / "S07-001.csv"
    if not csv.exists():
        print(f"{csv} not found: the real-performance case is skipped", file=sys.stderr)
        return None
    rig = Rig.load(shared / "ict-face")
    layout = MarkerLayout.load(shared / "ict-face" / "markers.json", rig)
    with tempfile.TemporaryDirectory() as tmp:
        with open(os.devnull, "w") as null:
            stdout, sys.stdout = sys.stdout, null
            try:
                livecap(["generate", "--rig", str(shared / "ict-face"), "--curves", str(csv), "--seconds",
                         str(seconds), "--rate", "120", "--out", tmp])
            finally:
                sys.stdout = stdout
        take = read_take(Path(tmp) / "S07-001.c3d")
        neutral = read_take(Path(tmp) / "S07-001_neutral.c3d")
        truth = GroundTruth.load(Path(tmp) / "S07-001.truth.npz")
    profile = calibrate(rig, layout, estimate_neutral(neutral.select(layout.labels), layout.stable, int(neutral.rate)))
    tune_on_take(profile, take)
    return "ICT, real performance (S07-001)", profile, take, truth.weights


def _labeller_at(rev: str):
    """``solvers/labelling.py`` at git revision ``rev``, imported as its own module."""
    import importlib.util
    import subprocess
    import tempfile

    root = Path(__file__).resolve().parents[1]
    text = subprocess.run(["git", "-C", str(root), "show", f"{rev}:solvers/labelling.py"], check=True,
                          capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "labelling_at_rev.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("labelling_at_rev", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["labelling_at_rev"] = module
    spec.loader.exec_module(module)
    return module


def _step_time(profile, take, quick: bool, mode: str = "robust", baseline=None) -> dict:
    """Per-frame CPU time (``time.thread_time_ns``: the machine is shared, CPU time is less noisy
    than wall time) of ``labeller.step`` on a scrambled take's clouds and, interleaved frame by
    frame under the same load, of the ``mode`` solver's step on the same take's labelled frames.
    With a ``baseline`` labeller the two labellers swap places every frame (one before the solver,
    one after it): right after the solver's step the caches are colder (a lean step loses ~5 % there)."""
    import time

    import numpy as np

    from livecap.demo.unlabelled import scramble
    from livecap.live.unlabelled import labeller_for
    from livecap.modes.registry import build_solver
    from livecap.offline.solve import prepare_targets

    sc = scramble(take.select(profile.labels), seed=5)
    clouds = [sc.cloud.positions[f, sc.cloud.valid[f]] for f in range(sc.cloud.n_frames)]
    occluded, targets, _, _ = prepare_targets(sc.occluded, profile)
    lab = labeller_for(profile)
    old = None if baseline is None else baseline.MarkerLabeller(profile.source_neutral, profile.stable,
                                                                profile.basis, profile.lower, profile.upper)
    solver = build_solver(mode, profile, {})
    lab.step(clouds[0])
    if old is not None:
        old.step(clouds[0])
    n = min(len(clouds) - 1, 500 if quick else 2000)
    t_lab, t_solve, t_old = np.empty(n), np.empty(n), np.empty(n)
    clock = time.thread_time_ns
    for i in range(n):
        f = 1 + i
        first, second = (old, lab) if old is not None and i % 2 else (lab, old)
        t0 = clock()
        first.step(clouds[f])
        t1 = clock()
        solver.step(targets[f], occluded.valid[f])
        t2 = clock()
        if second is not None:
            second.step(clouds[f])
        t3 = clock()
        t_lab[i], t_old[i] = (t1 - t0, t3 - t2) if first is lab else (t3 - t2, t1 - t0)
        t_solve[i] = t2 - t1
    out = {}
    for key, t in (("label", t_lab), ("solve", t_solve)) + ((("baseline", t_old),) if old is not None else ()):
        out[f"{key}_median_us"] = float(np.median(t)) / 1e3
        out[f"{key}_p99_us"] = float(np.percentile(t, 99)) / 1e3
    return out


def run(quick: bool = False, against: tuple[str, ...] = ("",)) -> dict:
    import os

    from livecap.offline.labelling import labelling_study

    baseline = _labeller_at(against[0]) if against and against[0] else None
    rows = []
    load = [os.getloadavg()[0]]
    for name, profile, take, truth in cases(quick):
        st = labelling_study(take, profile, truth, seed=1)
        step = _step_time(profile, take, quick, baseline=baseline)
        load.append(os.getloadavg()[0])
        rows.append({
            "take": name, "frames": take.n_frames, "markers": len(profile.labels),
            "right_pct": 100 * st.scores.right, "longest_swap": st.scores.longest_swap,
            "unlabelled": st.scores.unlabelled, "ghosts_labelled": st.scores.ghost_labelled,
            "rmse_labelled": st.rmse_labelled, "rmse_unlabelled": st.rmse_unlabelled,
            "rmse_ratio": st.rmse_ratio, **step, "label_over_solve": step["label_median_us"] / step["solve_median_us"],
            "inits": st.initialisations,
        })
    print(table(rows, ["take", "frames", "right_pct", "longest_swap", "unlabelled", "ghosts_labelled",
                       "rmse_labelled", "rmse_unlabelled", "rmse_ratio", "label_median_us", "label_p99_us",
                       "solve_median_us", "solve_p99_us", "label_over_solve", "inits"]
                + (["baseline_median_us", "baseline_p99_us"] if baseline is not None else []),
                "labelling unlabelled clouds (2 ghosts/frame, occlusion to 5 %, robust solve; "
                "per-frame CPU time)"))
    print(f"load average (1 min) during the run: {min(load):.1f}-{max(load):.1f}")
    return {"rows": rows, "ghosts": 2, "occlusion": 0.05, "mode": "robust", "load": load,
            "baseline_rev": against[0] if baseline is not None else None}


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__, against=""))
