"""Where the ICT weight error with a prior from the other files goes (issue 41: streamed <= 0.35x, offline <= 0.25x).

Per held-out file and noise, ``kalman`` (the default with a prior) streamed as ``livecap run`` feeds it and offline as
``livecap solve`` runs it, the prior built from the other five files as ``livecap realeval`` builds it; the weight
RMSE as a ratio to the oracle's, and the same RMSE with one part of the error taken out at a time:

- ``no bias``: every shape's constant bias (its mean error over the take) subtracted -- what the prior mean's pull and
  any other constant offset cost;
- ``no mouth bias``: only the bias of the shapes issue 41 names (mouthShrugUpper, mouthFunnel, mouthLowerDown);
- ``eye pair true``: eyeSquint_L/_R and eyeLookUp_L/_R set to the truth (the pair the markers see as one, cosine 0.94);
- ``first 1.5 s / 3 s true`` (streamed): the frames before the first check is used / before the second set to truth;
- ``strength K``: the prior's strength held at ``marker_kalman.STRENGTHS[K]`` all take (streamed: the weak hold too),
  for the best strength per file and the best single strength for every file, in hindsight (bounds, not methods).

    python -m benchmarks.prior_gap --noise 0.5 0.2 --seconds 10 [--strengths 0 1 2 3 4 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

MOUTH = ("mouthShrugUpper", "mouthFunnel", "mouthLowerDown_L", "mouthLowerDown_R")
EYES = ("eyeSquint_L", "eyeSquint_R", "eyeLookUp_L", "eyeLookUp_R")


def parts(W: np.ndarray, truth: np.ndarray, names: list[str], rate: float, streamed: bool) -> dict[str, float]:
    """The weight RMSE of ``W`` and of ``W`` with one part of its error taken out at a time (see the module doc)."""
    def rmse(X: np.ndarray) -> float:
        return float(np.sqrt(np.mean((X - truth) ** 2)))

    bias = (W - truth).mean(0)
    out = {"rmse": rmse(W), "no bias": rmse(W - bias)}
    mouth = [names.index(n) for n in MOUTH if n in names]
    X = W.copy()
    X[:, mouth] -= bias[mouth]
    out["no mouth bias"] = rmse(X)
    eyes = [names.index(n) for n in EYES if n in names]
    X = W.copy()
    X[:, eyes] = truth[:, eyes]
    out["eye pair true"] = rmse(X)
    if streamed:
        for s in (1.5, 3.0):
            X = W.copy()
            X[: int(s * rate)] = truth[: int(s * rate)]
            out[f"first {s:g} s true"] = rmse(X)
    return out


def main(argv: list[str] | None = None) -> int:
    from livecap.calibration.animation_prior import build_prior
    from livecap.cli.realeval import _realdata, _rig
    from livecap.demo.curves_take import CurveTakeSettings, curves_take, take_seed
    from livecap.modes import marker_kalman
    from livecap.offline.real_eval import oracle_weights, plain_profile
    from livecap.offline.solve import solve_take
    from livecap.offline.streamed import stream_take
    from transport.llf_csv import read_llf_csv

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--noise", type=float, nargs="+", default=[0.5, 0.2])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--strengths", type=int, nargs="*", default=[0, 1, 2, 3, 4, 5])
    p.add_argument("--files", nargs="+")
    p.add_argument("--no-stream", action="store_true")
    p.add_argument("--no-prior", action="store_true", help="the ridge instead (whose biases are not the prior's)")
    p.add_argument("--seed", type=int, default=1, help="base seed of the takes' noise, occlusion and neutral draw, "
                   "one per file from it and the file's name (curves_take.take_seed; 1: realeval's)")
    p.add_argument("--draw", type=int, default=0, help="the draw index (realeval --draws N runs 0..N-1; default 0)")
    p.add_argument("--json")
    args = p.parse_args(argv)
    rig, layout = _rig("ict")
    files = sorted((_realdata() / "performance").glob("*.csv"))
    names = list(rig.names)
    Solver = marker_kalman.MarkerKalmanSolver
    strength, chosen = Solver._strength, marker_kalman.take_strength
    evidence_pick = getattr(Solver, "_evidence_pick", None)  # (a tree before branch prior11 has none)
    out = []
    for noise in args.noise:
        for f in files:
            if args.files and f.stem not in args.files:
                continue
            start = max(0.0, min(10.0, read_llf_csv(f).times[-1] - args.seconds))
            seed = take_seed(f, args.seed, args.draw)
            ct = curves_take(rig, layout, f, CurveTakeSettings(start=start, seconds=args.seconds, noise_mm=noise,
                                                                      seed=seed))
            prior = build_prior([o for o in files if o != f], rig.names, rig.lower, rig.upper)
            profile = plain_profile(rig, layout, ct)
            profile.prior = None if args.no_prior else prior
            opts = {"rate": ct.take.rate}
            oracle = float(np.sqrt(np.mean((oracle_weights(ct, rig.lower, rig.upper) - ct.weights) ** 2)))
            for k in [None, *args.strengths]:
                def held(self, k=k):
                    return k

                def take_strength(*a, k=k, **kw):
                    best, err, used = chosen(*a, **kw)
                    return k, err, used

                if k is not None:
                    Solver._strength = held
                    marker_kalman.take_strength = take_strength
                    Solver._evidence_pick = lambda self, *a: len(marker_kalman.STRENGTHS)  # held: no other choice
                try:
                    t0 = time.perf_counter()
                    runs = [] if args.no_stream else [("stream", stream_take(ct.take, profile, "kalman", opts).weights)]
                    solver = marker_kalman.kalman_mode(profile, opts)
                    runs.append(("offline", solve_take(ct.take, profile, solver).weights))
                finally:
                    Solver._strength, marker_kalman.take_strength = strength, chosen
                    if evidence_pick is not None:
                        Solver._evidence_pick = evidence_pick
                for path, W in runs:
                    rec = {"noise_mm": noise, "file": f.stem, "seed": seed, "path": path, "strength": k,
                           "oracle": oracle,
                           **{key: v / oracle for key, v in parts(W, ct.weights, names, ct.take.rate,
                                                                  path == "stream").items()},
                           "bias": dict(sorted(zip(names, (W - ct.weights).mean(0).tolist(), strict=True),
                                               key=lambda kv: -abs(kv[1]))[:6]),
                           "bias_all": ((W - ct.weights).mean(0) / oracle).tolist()}
                    out.append(rec)
                    shown = {key: v for key, v in rec.items()
                             if isinstance(v, float) and key not in ("oracle", "noise_mm")}
                    print(f"{noise:g} {f.stem[:12]:12s} {path:7s} K={k} " + " ".join(
                        f"{key} {v:.3f}" for key, v in shown.items())
                        + f" [{time.perf_counter() - t0:.0f} s]", flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"machine": platform.node(), "date": time.strftime("%Y-%m-%d %H:%M"),
                                               "load": Path("/proc/loadavg").read_text().split()[:3],
                                               "argv": sys.argv[1:] if argv is None else argv, "rows": out}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
