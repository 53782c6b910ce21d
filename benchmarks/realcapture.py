"""Plausibility of solves on real optical captures (issue 35): AnimFace takes bound to the ICT rig.

Per take and mode: ``livecap markers bind`` in process, calibration on the first second (near
neutral), tuning on the take (as ``livecap calibrate --tune TAKE``), a whole-take solve, then the
metrics of :mod:`livecap.offline.plausibility`: weight sum over the first second, largest eye-gaze
weight, mean mouthFrown, per-shape activity on frames where the shape's markers are still, the
main shapes' correlation with the marker geometry (one-sided: its change from the neutral clipped at 0, as a
weight is; the signed figure beside it), and the share of single-frame jumps > 0.1; the same,
with the weight RMSE and phantom activity against the truth, on model-mismatch takes (the MakeHuman head
acting real curves, its markers bound to ICT: ``livecap generate --actor-rig``). ``--streamed``: the weights as
the live pipeline streams them (``livecap.offline.streamed.stream_take``: frame by frame, causal head pose, the
mode's latency aligned), measured against the same stabilised markers.

    python -m benchmarks.realcapture [--modes auto,movement] [--takes JawMoCap,CheeksMoCap] [--mismatch S07-001,apfel]
                                     [--streamed]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from livecap.offline.plausibility import Signal

# AnimFace names (capture-animface/README.md); +y up in the head frame
SIGNALS = [
    Signal("jawOpen", "distance", ("Chin", "NoseHead")),
    Signal("mouthSmile_L", "rise", ("Mouth_Lend",)),
    Signal("mouthSmile_R", "rise", ("Mouth_Rend",)),
    Signal("mouthSmile_L", "distance", ("Mouth_Lend", "Mouth_Rend")),
    Signal("browInnerUp_L", "rise", ("Leyebrow_Inside",)),
    Signal("browOuterUp_L", "rise", ("Leyebrow_Outside",)),
    Signal("browOuterUp_R", "rise", ("Reyebrow_Outside",)),
]

# the same geometry on the model-mismatch takes, whose markers carry ICT's multi-PIE labels (+x the actor's left)
MISMATCH_SIGNALS = [
    Signal("jawOpen", "distance", ("M08_jaw", "M30_nose")),
    Signal("mouthSmile_L", "rise", ("M54_lip",)),
    Signal("mouthSmile_R", "rise", ("M48_lip",)),
    Signal("mouthSmile_L", "distance", ("M54_lip", "M48_lip")),
    Signal("browInnerUp_L", "rise", ("M22_brow",)),
    Signal("browOuterUp_L", "rise", ("M26_brow",)),
    Signal("browOuterUp_R", "rise", ("M17_brow",)),
]


def metrics(profile, solved, signals, first: int) -> dict:
    """The plausibility figures of one solve (``first``: frames of the near-neutral start), with what says where
    a phantom comes from: the per-marker residual and the shapes each phantom (mouthFrown, the strongest eye
    gaze) moves with."""
    from livecap.offline import plausibility as pl

    W, names = solved.weights, list(profile.names)
    frown = [j for j, n in enumerate(names) if n.startswith("mouthFrown")]
    quiet = pl.quiet_activity(W, solved.targets, solved.valid, pl.shape_markers(profile.basis))
    worst = np.argsort(-np.nan_to_num(quiet))[:3]
    jumps, per_shape = pl.jump_share(W)
    resid = pl.marker_residual(W, profile.basis, solved.targets, solved.valid)
    phantoms = [names[j] for j in frown]
    gaze = [j for j, n in enumerate(names) if pl.GAZE.search(n)]
    if gaze:
        phantoms.append(names[gaze[int(np.argmax(W[:, gaze].max(axis=0)))]])
    return {"resid_worst": [(profile.labels[i], float(resid[i])) for i in np.argsort(-resid)[:4]],
            "resid_rms": float(np.sqrt(np.mean(resid**2))),
            "partners": {p: pl.partners(W, names, p) for p in phantoms},
            "sum_first_s": pl.weight_sum(W, slice(0, first)), "gaze_max": pl.max_weight(W, names),
            "frown_mean": float(W[:, frown].mean()), "quiet_worst": [(names[j], float(quiet[j])) for j in worst],
            "corr": pl.signal_correlations(signals, names, W, profile.labels, solved.targets, profile.source_neutral),
            "corr_signed": pl.signal_correlations(signals, names, W, profile.labels, solved.targets,
                                                  profile.source_neutral, one_sided=False),
            "jumps": jumps, "jumpiest": names[int(np.argmax(per_shape))]}


def solve(take, profile, mode: str, streamed: bool):
    """The whole-take solve, or (``streamed``) the same with the live pipeline's weights in place of its own."""
    from dataclasses import replace

    from livecap.modes.registry import build_solver
    from livecap.offline.solve import solve_take

    solved = solve_take(take, profile, build_solver(mode, profile, {}))
    if not streamed:
        return solved
    from livecap.offline.streamed import stream_take

    return replace(solved, weights=stream_take(take, profile, mode).weights)


def _name(mode: str, profile, streamed: bool) -> str:
    from livecap.modes.registry import resolve_mode

    return resolve_mode(mode, profile) + (" streamed" if streamed else "")


def run_mismatch(curves: str, modes: list[str], seconds: float = 20.0, streamed: bool = False) -> list[dict]:
    """The MakeHuman head performing ``curves`` (a performance in realdata/performance), bound to ICT: the same
    figures, plus the weight RMSE and phantom activity against the truth (what the actor did on ICT's shapes,
    livecap.demo.mismatch_take) and, beside it, the RMSE against the driving curves."""
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.cli.realeval import _realdata
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.demo.mismatch_take import MismatchSettings, mismatch_take
    from livecap.offline.setup import tune_on_take
    from transport.arkit import load_mapping

    real = _realdata()
    ict, mh = Rig.load(real / "ict-face"), Rig.load(real / "makehuman-head")
    mapping = load_mapping(Path(__file__).resolve().parents[1] / "examples" / "makehuman_arkit.json")
    mt = mismatch_take(mh, ict, MarkerLayout.load(real / "ict-face" / "markers.json", ict),
                       real / "performance" / f"{curves}.csv", mapping, MismatchSettings(seconds=seconds, start=10.0))
    profile = calibrate(ict, mt.layout, estimate_neutral(mt.neutral.select(mt.layout.labels), mt.layout.stable))
    tuned = tune_on_take(profile, mt.take)  # once: no solver changes the profile
    # the binding against the true anatomy: the actor's markers sit at ICT's own sites (mismatch_take.actor_sites)
    truth = MarkerLayout.load(real / "ict-face" / "markers.json", ict)
    true_sites = dict(zip(truth.labels, truth.sampling_matrix(ict.n_vertices) @ ict.neutral, strict=True))
    site_err = np.linalg.norm(mt.layout.sampling_matrix(ict.n_vertices) @ ict.neutral
                              - np.array([true_sites[lab] for lab in mt.layout.labels]), axis=1)
    rows = []
    for mode in modes:
        solved = solve(mt.take, profile, mode, streamed)
        rest = mt.weights < 0.01
        rows.append({"take": f"{curves} (MakeHuman -> ICT)", "mode": _name(mode, profile, streamed),
                     "noise_mm": tuned["noise_mm"], "frames": mt.take.n_frames,
                     "rmse": float(np.sqrt(np.mean((solved.weights - mt.weights) ** 2))),
                     "rmse_curves": float(np.sqrt(np.mean((solved.weights - mt.curves) ** 2))),
                     "phantom": float(solved.weights[rest].mean()),
                     "site_error_mm": (float(np.median(site_err)), float(site_err.max())),
                     **metrics(profile, solved, MISMATCH_SIGNALS, int(round(mt.take.rate)))})
    return rows


def run_take(name: str, modes: list[str], streamed: bool = False) -> list[dict]:
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.cli.realeval import _realdata
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.offline.setup import tune_on_take
    from livecap.transfer.bind import bind_capture
    from transport.takefile import read_take

    path, ict = _realdata() / "capture-animface" / f"{name}.c3d", _realdata() / "ict-face"
    if not path.exists() or not ict.exists():
        raise SystemExit(f"realcapture: no {path} or {ict}")
    take = read_take(path)
    rig = Rig.load(ict)
    layout = bind_capture(take, rig, MarkerLayout.load(ict / "markers.json", rig)).layout(rig)
    sel = take.select(layout.labels)
    second = int(round(take.rate))
    profile = calibrate(rig, layout, estimate_neutral(sel, layout.stable, second))
    tuned = tune_on_take(profile, take)  # once: no solver changes the profile
    rows = []
    for mode in modes:
        t0 = time.perf_counter()
        solved = solve(take, profile, mode, streamed)
        seconds = time.perf_counter() - t0
        rows.append({"take": name, "mode": _name(mode, profile, streamed), "noise_mm": tuned["noise_mm"],
                     "solve_s": seconds, "frames": take.n_frames, **metrics(profile, solved, SIGNALS, second)})
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--modes", default="auto,movement", help="comma list of modes (default auto,movement)")
    p.add_argument("--takes", default="JawMoCap,CheeksMoCap", help="comma list of AnimFace takes")
    p.add_argument("--mismatch", default="S07-001,apfel", help="performances the MakeHuman head acts, bound to "
                   "ICT (model mismatch with truth); 'none' to skip")
    p.add_argument("--streamed", action="store_true", help="the weights as the live pipeline streams the take "
                   "(causal) instead of the whole-take solve")
    args = p.parse_args(argv)
    modes = args.modes.split(",")
    runs = [run_take(name, modes, args.streamed) for name in args.takes.split(",")]
    if args.mismatch != "none":
        runs += [run_mismatch(c, modes, streamed=args.streamed) for c in args.mismatch.split(",")]
    for r in (row for rows in runs for row in rows):
        if "rmse" in r:
            print(f"{r['take']} {r['mode']}: weight RMSE vs what the actor did {r['rmse']:.3f} "
                  f"(vs the curves {r['rmse_curves']:.3f}), phantom {r['phantom']:.3f}; "
                  "bound sites from the true ones median {:.2f} max {:.2f} mm".format(*r["site_error_mm"]))
        print(f"{r['take']} {r['mode']}: noise {r['noise_mm']:.3f} mm; weight sum over the first second mean "
              f"{r['sum_first_s'][0]:.3f} max {r['sum_first_s'][1]:.3f}; eye gaze max {r['gaze_max']:.3f}; "
              f"mouthFrown mean {r['frown_mean']:.3f}; jumps > 0.1 on {r['jumps'] * 100:.1f} % of frames "
              f"(most: {r['jumpiest']}); {r['frames']} frames")
        print(f"   residual {r['resid_rms']:.2f} mm RMS, worst: "
              + ", ".join(f"{n} {v:.2f}" for n, v in r["resid_worst"]))
        print("   moves with: " + "; ".join(f"{p} ~ " + ", ".join(f"{n} r={c:.2f}" for n, c in ps)
                                          for p, ps in r["partners"].items()))
        print("   still-marker activity, worst: " + ", ".join(f"{n} {v:.3f}" for n, v in r["quiet_worst"]))
        print("   " + "; ".join(f"{k} r={v:.2f} (signed {r['corr_signed'][k]:.2f})" for k, v in r["corr"].items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
