"""kalman's marker-space QPs at 72 x 1000 recorded and replayed (issue 39 item 1): where a frame's fit and trial go.

``record``: kalman streamed over the synthetic 72 x 1000 take (``benchmarks.synthetic``, every marker seen), every
``MarkerSpaceQP`` built (J, D, limits) and every ``begin`` / ``solve`` call on it (f, start), tagged with the frame
and whether the fit or a held-out trial made it, saved to an .npz. ``replay``: the same calls in the same order on
solvers built by the tree on PYTHONPATH (thread CPU per call and per frame, passes and refactors counted, the
solutions beside the recorded ones): the solver's own cost, without the rest of kalman's step, so that variants of
solvers/marker_space_qp.py can be alternated with main's in one process-free loop. A solve's peer (``near``: the
QP whose kept S it may start from) and a begin's ``now`` are recorded and replayed where the recording has them (a
recording by a tree without them replays on any tree; one with them only on a tree whose solver takes them).

    PYTHONPATH=$PWD python benchmarks/marker_space_fit.py record /tmp/ms.npz
    PYTHONPATH=<tree> python benchmarks/marker_space_fit.py replay /tmp/ms.npz [--json out.json]

``stream``: kalman over the synthetic take (``--seed``, ``--noise``), thread CPU per step and the weights' RMSE
against its truth; the weights saved to PATH, or compared with those saved there by another run:

    PYTHONPATH=$PWD python benchmarks/marker_space_fit.py stream /tmp/w.npy [--set STREAM_PASSES=0] [--no-trial]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

WARMUP = 50


def record(path: str, frames: int = 400, size: tuple[int, int] = (72, 1000)) -> dict:
    """Stream kalman over the synthetic take with MarkerSpaceQP's constructor, ``begin`` and ``solve`` wrapped."""
    import solvers.marker_space_qp as msq
    from benchmarks.kalman_step import _build, synthetic_case
    from solvers.prior_strength import HeldOutStrength

    profile, targets, valid, options = synthetic_case(*size, frames)
    built: list[tuple] = []
    calls: list[tuple] = []
    ids: dict[int, int] = {}
    state = {"frame": -1, "trial": False}
    cls = msq.MarkerSpaceQP
    init, begin, solve = cls.__init__, cls.begin, cls.solve

    def w_init(self, J, d, lower, upper, max_iter=200, whole=None, same=None):  # (replayed without them: the same
        ids[id(self)] = len(built)  # x, S to rounding)
        built.append((np.array(J, float), np.array(d, float), np.array(lower, float), np.array(upper, float)))
        init(self, J, d, lower, upper, max_iter, whole, same)

    def peer(near):  # the peer a solve may take its S from (MarkerSpaceQP ``near``): its index, our rows in its rows
        rows = np.full(3 * profile.n_markers, -1)
        if near is None:
            return -1, rows
        rows[:len(near[1])] = near[1]
        return ids[id(near[0])], rows

    def w_begin(self, f, x0, passes, frame_passes=0, near=None, now=None):
        calls.append((state["frame"], ids[id(self)], 1, int(state["trial"]), int(passes), np.array(f), np.array(x0),
                      frame_passes, -1 if now is None else int(now), *peer(near)))
        return begin(self, f, x0, passes, frame_passes, near, now)

    def w_solve(self, f, x0, frame_passes=0, near=None):
        calls.append((state["frame"], ids[id(self)], 0, int(state["trial"]), 0, np.array(f), np.array(x0),
                      frame_passes, -1, *peer(near)))
        return solve(self, f, x0, frame_passes, near)

    observe, hs_begin = HeldOutStrength.observe, HeldOutStrength.begin

    def in_trial(fn):
        def run(*a, **k):
            state["trial"] = True
            try:
                return fn(*a, **k)
            finally:
                state["trial"] = False
        return run

    cls.__init__, cls.begin, cls.solve = w_init, w_begin, w_solve
    HeldOutStrength.observe, HeldOutStrength.begin = in_trial(observe), in_trial(hs_begin)
    try:
        solver = _build(profile, options, "kalman")
        W = []
        for i in range(len(targets)):
            state["frame"] = i
            W.append(solver.step(targets[i], valid[i]))
    finally:
        cls.__init__, cls.begin, cls.solve = init, begin, solve
        HeldOutStrength.observe, HeldOutStrength.begin = observe, hs_begin
    names = ("J", "d", "lower", "upper")
    np.savez(path, **{f"{k}{i}": a for i, b in enumerate(built) for k, a in zip(names, b, strict=True)},
             built=len(built), frame=np.array([c[0] for c in calls]), qp=np.array([c[1] for c in calls]),
             begin=np.array([c[2] for c in calls]), trial=np.array([c[3] for c in calls]),
             passes=np.array([c[4] for c in calls]), f=np.array([c[5] for c in calls]),
             x0=np.array([c[6] for c in calls]), frame_passes=np.array([c[7] for c in calls]),
             now=np.array([c[8] for c in calls]), peer=np.array([c[9] for c in calls]),
             peer_rows=np.array([c[10] for c in calls]))
    return {"qps": len(built), "calls": len(calls), "frames": len(targets)}


def replay(path: str) -> dict:
    """The recorded calls on this tree's MarkerSpaceQP, in order: thread CPU per frame (fit and trial apart), passes
    and refactors per call, the largest difference from a fresh exact solve is not computed here (see ``exact``)."""
    import solvers.marker_space_qp as msq

    z = dict(np.load(path))  # (an NpzFile reads an array anew at every lookup)
    qps = [msq.MarkerSpaceQP(z[f"J{i}"], z[f"d{i}"], z[f"lower{i}"], z[f"upper{i}"]) for i in range(int(z["built"]))]
    counts = {"refactor": 0, "changed": 0}
    refactor = msq.MarkerSpaceQP._refactor

    def counted(self, F, changed, *a):
        counts["refactor"] += 1
        counts["changed"] += len(changed)
        return refactor(self, F, changed, *a)

    msq.MarkerSpaceQP._refactor = counted
    T = int(z["frame"].max()) + 1
    cost = {"fit": np.zeros(T), "trial": np.zeros(T)}
    refactors = {"fit": np.zeros(T), "trial": np.zeros(T)}
    passes = {"fit": np.zeros(T), "trial": np.zeros(T)}
    X = np.full(z["x0"].shape, np.nan)
    thread = time.thread_time_ns
    try:
        for c in range(len(z["frame"])):
            q, fr, kind = qps[z["qp"][c]], z["frame"][c], "trial" if z["trial"][c] else "fit"
            counts["refactor"] = 0
            c0 = thread()
            extra = {}  # a recording by a tree whose solves take a peer's S / begin fewer passes now
            if "peer" in z and z["peer"][c] >= 0:
                extra["near"] = (qps[z["peer"][c]], z["peer_rows"][c][z["peer_rows"][c] >= 0])
            if z["begin"][c]:
                if "now" in z and z["now"][c] >= 0:
                    extra["now"] = int(z["now"][c])
                q.begin(z["f"][c], z["x0"][c], int(z["passes"][c]), int(z["frame_passes"][c]), **extra)
            else:
                x = q.solve(z["f"][c], z["x0"][c], int(z["frame_passes"][c]), **extra)
            cost[kind][fr] += (thread() - c0) / 1e3
            refactors[kind][fr] += counts["refactor"]
            if not z["begin"][c]:
                passes[kind][fr] += q.iterations
                if x is not None:
                    X[c] = x
    finally:
        msq.MarkerSpaceQP._refactor = refactor
    total = cost["fit"] + cost["trial"]

    def stats(a):
        a = a[WARMUP:]
        return {"p50": float(np.median(a)), "p99": float(np.percentile(a, 99)), "mean": float(a.mean())}

    worst = np.argsort(total[WARMUP:])[-4:] + WARMUP
    return {"fit": stats(cost["fit"]), "trial": stats(cost["trial"]), "fit + trial": stats(total),
            "fit passes (solves) mean": float(passes["fit"][WARMUP:].mean()),
            "fit refactors mean": float(refactors["fit"][WARMUP:].mean()),
            "trial refactors mean": float(refactors["trial"][WARMUP:].mean()),
            "worst frames": [{"frame": int(i), "fit": float(cost["fit"][i]), "trial": float(cost["trial"][i]),
                              "fit refactors": int(refactors["fit"][i]),
                              "trial refactors": int(refactors["trial"][i])} for i in worst],
            "_X": X}


def stream(frames: int = 400, no_trial: bool = False, seed: int = 1, noise_mm: float = 0.3,
           size: tuple[int, int] = (72, 1000), hidden: int = 0) -> dict:
    """kalman streamed over the synthetic take (``size``: markers, shapes; its noise ``seed`` and level): thread CPU
    (and wall) per ``step`` after WARMUP frames and the weights' RMSE against the take's truth (the same frames);
    the weights under ``_W``. ``hidden``: that many markers hidden at a time, another set every 20 frames (the
    visibility pattern changes and comes back: a fit on a pattern new to its QP, or on one it left frames ago)."""
    from benchmarks.kalman_step import _build
    from benchmarks.synthetic import synthetic_profile, synthetic_stream

    profile = synthetic_profile(*size)
    targets, valid, truth = synthetic_stream(profile, frames, noise_mm=noise_mm, seed=seed)
    if hidden:
        n = valid.shape[1]
        for t in range(frames):
            valid[t, (np.arange(hidden) * (n // hidden) + t // 20) % n] = False
    solver = _build(profile, {}, "kalman")
    if no_trial:
        solver._trial = lambda *a, **k: None
    W, cpu, wall = np.empty((frames, truth.shape[1])), np.empty(frames), np.empty(frames)
    thread, clock = time.thread_time_ns, time.perf_counter_ns
    for i in range(frames):
        c0, t0 = thread(), clock()
        W[i] = solver.step(targets[i], valid[i])
        t1, c1 = clock(), thread()
        cpu[i], wall[i] = (c1 - c0) / 1e3, (t1 - t0) / 1e3
    c, w = cpu[WARMUP:], wall[WARMUP:]
    return {"p50": float(np.median(c)), "p99": float(np.percentile(c, 99)), "mean": float(c.mean()),
            "wall p50": float(np.median(w)), "wall p99": float(np.percentile(w, 99)), "wall mean": float(w.mean()),
            "rmse": float(np.sqrt(np.mean((W[WARMUP:] - truth[WARMUP:]) ** 2))), "_W": W}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=["record", "replay", "stream"])
    p.add_argument("path")
    p.add_argument("--frames", type=int, default=400)
    p.add_argument("--json")
    p.add_argument("--solutions", help="replay: save the solutions (.npy) / compare with ones saved so")
    p.add_argument("--seed", type=int, default=1, help="stream: the take's noise seed (default 1)")
    p.add_argument("--noise", type=float, default=0.3, help="stream: marker noise, mm (default 0.3)")
    p.add_argument("--set", nargs="*", default=[], metavar="NAME=INT",
                   help="constants of solvers.marker_space_qp, solvers.prior_strength or livecap.modes.marker_kalman "
                        "for this run (e.g. STREAM_PASSES=0: the exact solve)")
    p.add_argument("--hidden", type=int, default=0, help="stream: markers hidden at a time, moved every 20 frames")
    p.add_argument("--no-trial", action="store_true", help="stream: kalman with its strength trial switched off")
    a = p.parse_args()
    import livecap.modes.marker_kalman as mk
    import solvers.marker_space_qp as msq
    import solvers.prior_strength as ps

    for item in a.set:
        name, value = item.split("=")
        module = next((m for m in (msq, ps, mk) if hasattr(m, name)), None)
        if module is None:
            p.error(f"--set: no constant {name} in solvers.marker_space_qp, solvers.prior_strength or "
                    "livecap.modes.marker_kalman")
        setattr(module, name, int(value))
    meta = {"utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "load": os.getloadavg()}
    if a.what == "record":
        out = record(a.path, a.frames)
    elif a.what == "stream":  # path: the weights (.npy), saved, or compared with where it exists
        out = stream(a.frames, a.no_trial, a.seed, a.noise, hidden=a.hidden)
        W = out.pop("_W")
        if Path(a.path).exists():
            out["max |dw| vs saved"] = float(np.abs(W - np.load(a.path)).max())
        else:
            np.save(a.path, W)
    else:
        out = replay(a.path)
        X = out.pop("_X")
        if a.solutions and Path(a.solutions).exists():
            Y = np.load(a.solutions)
            both = ~np.isnan(X).any(1) & ~np.isnan(Y).any(1)
            out["max |dx| vs saved"] = float(np.abs(X[both] - Y[both]).max())
        elif a.solutions:
            np.save(a.solutions, X)
    out = {"start": meta, "set": a.set, "result": out, "end_load": os.getloadavg()}
    print(json.dumps(out, indent=1))
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
