"""Where a streamed ``kalman`` with a prior loses the blinks and the first seconds (issue 41).

Leave one file out over ../shared/realdata/performance (the prior from the other files, as ``livecap realeval``
builds it), each take streamed frame by frame through the live pipeline (livecap.offline.streamed) as ``realeval``'s
``stream`` rows are. Per take: weight RMSE, jitter x truth, blink retention of the output and of the fit's own
weights before the weight stage (solvers.tracking.RotatedIMM's input), the held-out strength index per 0.5 s, the
weight RMSE per time window; per true blink (truth > 0.5 on the rig's blink shapes): its peak kept by the output and
by the fit, the weight stage's largest 'move' probability and the held-out strength index at the peak.

``--strength K`` holds the fit at ``marker_kalman.STRENGTHS[K]`` throughout (the held-out trials still run);
``--no-prior`` a ridge. A diagnosis, not a mode: the fit's strength and the weight stage's input are read by wrapping
``MarkerKalmanSolver.step``, ``RotatedIMM.step`` and ``HeldOutStrength.best`` for the run.

    python -m benchmarks.prior_blink [--rig ict|RIG --markers M --mapping J] [--noise 0.5] [--strength K] [--json F]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

WINDOWS = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)  # s


@contextmanager
def _recorded(rec: dict, strength: int | None):
    """Each step's fit weights, output, largest 'move' probability and held-out choice into ``rec``."""
    from livecap.modes import marker_kalman as mk
    from solvers import tracking
    from solvers.prior_strength import HeldOutStrength

    imm_step, solver_step = tracking.RotatedIMM.step, mk.MarkerKalmanSolver.step

    def imm(self, y):
        out = imm_step(self, y)
        move = self.imm.move_probability
        rec["fit"].append(np.array(y))
        rec["move"].append(0.0 if move is None else float(move.max()))
        return out

    def step(self, target, valid):
        out = solver_step(self, target, valid)
        rec["chosen"].append(self.selector.best)
        return out

    tracking.RotatedIMM.step, mk.MarkerKalmanSolver.step = imm, step
    if strength is not None:
        HeldOutStrength.best = property(lambda self: strength, lambda self, v: None)
    try:
        yield
    finally:
        tracking.RotatedIMM.step, mk.MarkerKalmanSolver.step = imm_step, solver_step
        if strength is not None:
            del HeldOutStrength.best


def _lagged(a: list) -> np.ndarray:
    """A per-step record aligned to the frames (the mode's one frame of latency)."""
    a = np.asarray(a)
    return np.concatenate([a[1:], a[-1:]])


def main(argv: list[str] | None = None) -> int:
    from scipy.signal import find_peaks

    from livecap.calibration.animation_prior import build_prior
    from livecap.cli.realeval import _realdata, _rig
    from livecap.demo.curves_take import CurveTakeSettings, curves_take
    from livecap.offline.real_eval import blink_retention, plain_profile, score
    from livecap.offline.streamed import stream_take
    from transport.arkit import load_mapping
    from transport.llf_csv import read_llf_csv

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rig", default="ict")
    p.add_argument("--markers")
    p.add_argument("--mapping")
    p.add_argument("--noise", type=float, default=0.5)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--strength", type=int, help="hold the fit at STRENGTHS[K]")
    p.add_argument("--no-prior", action="store_true")
    p.add_argument("--json")
    args = p.parse_args(argv)
    rig, layout = _rig(args.rig, args.markers)
    mapping = load_mapping(args.mapping) if args.mapping else None
    files = sorted((_realdata() / "performance").glob("*.csv"))
    out = []
    for f in files:
        start = max(0.0, min(10.0, read_llf_csv(f).times[-1] - args.seconds))
        ct = curves_take(rig, layout, f, CurveTakeSettings(start=start, seconds=args.seconds, noise_mm=args.noise),
                         mapping)
        profile = plain_profile(rig, layout, ct)
        if not args.no_prior:
            profile.prior = build_prior([o for o in files if o != f], rig.names, rig.lower, rig.upper, mapping)
        rec = {"fit": [], "move": [], "chosen": []}
        with _recorded(rec, args.strength):
            st = stream_take(ct.take, profile, "kalman", {"rate": ct.take.rate})
        W, truth, rate = st.weights, ct.weights, ct.take.rate
        fit, move, chosen = _lagged(rec["fit"]), _lagged(rec["move"]), _lagged(rec["chosen"])
        row = score("kalman stream", rig, ct, W, st.seconds)
        blinks = []
        for b in ct.blinks:
            peaks, _ = find_peaks(truth[:, b], height=0.5, distance=max(1, int(0.2 * rate)))
            for t in peaks:
                near = slice(max(0, t - 2), t + 3)
                blinks.append({"shape": rig.names[b], "s": round(t / rate, 2), "true": float(truth[t, b]),
                               "kept": float(W[near, b].max() / truth[t, b]),
                               "fit_kept": float(fit[near, b].max() / truth[t, b]),
                               "move": float(move[near].max()), "strength": int(chosen[t])})
        windows = [float(np.sqrt(np.mean((W - truth)[int(a * rate):int(z * rate)] ** 2)))
                   for a, z in zip(WINDOWS[:-1], WINDOWS[1:], strict=True) if a * rate < len(W)]
        rec_out = {"file": f.stem, "rmse": row.rmse, "jitter_x": row.jitter_x, "blink": row.blink,
                   "blink_fit": blink_retention(ct.blinks, fit, truth, rate), "windows": windows,
                   "strength_per_half_s": chosen[::max(1, int(rate / 2))].tolist(), "blinks": blinks}
        out.append(rec_out)
        print(f"{f.stem[:24]:24s} RMSE {row.rmse:.4f} jitter {row.jitter_x:.2f} blink {row.blink:.3f} (fit "
              f"{rec_out['blink_fit']:.3f}) windows " + " ".join(f"{v:.3f}" for v in windows)
              + " strength " + "".join(map(str, rec_out["strength_per_half_s"])), flush=True)
        for q in blinks:
            print(f"    {q['shape']:20s} {q['s']:5.2f} s true {q['true']:.2f} kept {q['kept']:.2f} fit "
                  f"{q['fit_kept']:.2f} move {q['move']:.2f} strength {q['strength']}", flush=True)
    mean = {k: float(np.mean([r[k] for r in out])) for k in ("rmse", "jitter_x", "blink", "blink_fit")}
    print("mean " + "  ".join(f"{k} {v:.4f}" for k, v in mean.items()))
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": platform.node(), "date": time.strftime("%Y-%m-%d %H:%M"),
                                               "args": vars(args), "mean": mean, "rows": out}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
