"""``livecap calibrate`` (neutral take + rig -> profile) and ``livecap calibration-report``."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from livecap.calibration.profile import WARPS, Profile, estimate_neutral
from livecap.cli.common import (
    add_noise_argument,
    add_rig_arguments,
    load_rig,
    parse_span,
    progress_bar,
    tune_on_take,
)
from livecap.cli.progress import stage
from livecap.modes.registry import DEFAULT_MODE, MODES_AND_AUTO, resolve_mode
from livecap.modes.robust import ROBUST_MODES
from livecap.offline.setup import calibrate_neutral
from livecap.offline.solve import DEFAULT_MAX_GAP_SECONDS, DEFAULT_POSE_SMOOTHING_SECONDS
from transport.takefile import read_take


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="calibrate an actor to a rig from a neutral take, write a profile",
                       description="Neutral markers (robust over the take, head motion removed), RBF "
                                   "proportion warp of the rig's marker sites onto them, marker-space basis: "
                                   "one .npz that every solve command loads with --profile.")
    p.add_argument("neutral", help="neutral take (.c3d/.trc/.csv): the actor at rest, head may move")
    add_rig_arguments(p)
    p.add_argument("--out", required=True, help="profile to write (.npz)")
    p.add_argument("--warp", default="rbf", choices=WARPS, help="proportion match (default rbf, Seol 2012 §3.2)")
    p.add_argument("--seconds", type=float, help="use only the first SECONDS of the take (default: all)")
    p.add_argument("--span", metavar="START:END", help="use only this span of the take, in seconds (e.g. 12.5:14)")
    p.add_argument("--smoothing", type=float, default=0.0, help="RBF smoothing (0 = exact at the markers)")
    p.add_argument("--max-gap", type=float, default=DEFAULT_MAX_GAP_SECONDS,
                   help=f"offline gap fill: longest gap in seconds (default {DEFAULT_MAX_GAP_SECONDS}; 0 = off)")
    p.add_argument("--pose-smoothing", type=float, default=DEFAULT_POSE_SMOOTHING_SECONDS,
                   help="offline head-pose smoothing window in seconds (default "
                        f"{DEFAULT_POSE_SMOOTHING_SECONDS}; 0 = off)")
    p.add_argument("--tune", metavar="TAKE", help="a take of the actor performing (e.g. a range-of-motion take): "
                   "select the noise level and regularisation from it and store them in the profile "
                   "(default: from the neutral take)")
    p.add_argument("--plain-stabilise", action="store_true", help="plain Kabsch instead of the robust fit")
    add_noise_argument(p)
    p.add_argument("--prior", metavar="PRIOR.npz", help="animation prior for this rig ('livecap prior build'): stored "
                   "in the profile; every solve with it then defaults to the dense kalman fit under that prior")
    p.set_defaults(func=run_calibrate)

    r = sub.add_parser("calibration-report", help="solve a take with and without each calibration step",
                       description="Per-frame solve error of the calibrated pipeline against variants with "
                                   "stabilisation, proportion warp or gap filling switched off, and the head "
                                   "pose against ground truth when the take has one (<take>.truth.npz).")
    r.add_argument("take", help="marker take (.c3d/.trc/.csv)")
    add_rig_arguments(r)
    src = r.add_mutually_exclusive_group()
    src.add_argument("--neutral", help="neutral take to calibrate from (default: the take's first seconds)")
    src.add_argument("--profile", help="take the actor's neutral from this profile")
    r.add_argument("--neutral-seconds", type=float, default=1.0,
                   help="neutral span at the start of the take when neither --neutral nor --profile (default 1)")
    r.add_argument("--truth", help="ground truth .npz (default: <take>.truth.npz when present)")
    r.add_argument("--mode", default=DEFAULT_MODE, choices=sorted(MODES_AND_AUTO),
                   help=f"solver mode (default {DEFAULT_MODE}, as for solve; lsq is the unregularised baseline)")
    r.add_argument("--ridge", type=float, help="ridge weight (default: the mode's, or the one tuning selected)")
    r.add_argument("--stride", type=int, default=1, help="solve every STRIDE-th frame only (quicker; default 1)")
    r.add_argument("--per-frame", help="write per-frame errors of every variant to this CSV")
    r.set_defaults(func=run_report)


def run_calibrate(args: argparse.Namespace) -> int:
    rig, layout = load_rig(args)
    take = read_take(args.neutral)
    if args.span and args.seconds:
        raise ValueError("give --seconds or --span, not both")
    span = parse_span(args.span, take.rate, take.n_frames) if args.span else None
    profile = calibrate_neutral(rig, layout, take, take_path=args.neutral, rig_path=args.rig, seconds=args.seconds,
                                warp=args.warp, smoothing=args.smoothing, max_gap_seconds=args.max_gap,
                                pose_smoothing_seconds=args.pose_smoothing,
                                robust_stabilise=not args.plain_stabilise, prior=args.prior, span=span)
    sel = take.select(layout.labels)
    if span is not None:
        sel = sel.slice(*span)
    frames = profile.settings["neutral_frames"]  # what calibrate_neutral averaged over (--seconds, else all of sel)
    tune_path = args.tune or args.neutral  # every profile carries the noise estimate every mode needs
    with stage(f"tuning on {tune_path}"):
        tuned = tune_on_take(profile, read_take(args.tune) if args.tune else take, args.noise_mm)
    print(f"tuned     on {tune_path}: noise {tuned['noise_mm']:.3f} mm ({tuned['noise_source']}; jitter "
          f"{tuned['jitter_mm']:.3f}, fit residual {tuned['residual_mm']:.3f}), ridge {tuned['ridge']:.3g} "
          f"({tuned['criterion']})")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    profile.save(args.out)
    local, _, _ = profile.stabiliser().stabilise(sel.positions[:frames], sel.valid[:frames])
    spread = np.linalg.norm(local - profile.source_neutral, axis=2)[sel.valid[:frames]]
    print(f"neutral   {args.neutral}: {frames} frames, {layout.n_markers} markers "
          f"({int(layout.stable.sum())} stable), spread about the neutral {np.sqrt(np.mean(spread ** 2)):.3f} mm RMS")
    print(f"warp      {args.warp}: overall scale {profile.settings['scale']:.4f}, "
          f"fit at the markers {profile.settings['warp_fit_rms_mm']:.2e} mm RMS")
    print(f"basis     {profile.basis.shape[0]} x {profile.basis.shape[1]} "
          f"({len(profile.marker_rig.inbetweens)} in-betweens, {len(profile.marker_rig.correctives)} correctives "
          "warped too)")
    if profile.prior is not None:
        print(f"prior     {args.prior}: {profile.prior.frames} frames of {len(profile.prior.sources)} performances; "
              f"default mode {resolve_mode(DEFAULT_MODE, profile)}")
    else:
        share = tuned.get("active_fraction")
        print("acting    " + ("no evidence (a still take; --tune a take of the actor performing)" if share is None
                              else f"{tuned['acting']} ({share:.2f} of the shapes active a frame in the sparse fit)")
              + f": default mode {resolve_mode(DEFAULT_MODE, profile)}")
    print(f"profile   {args.out}")
    return 0


def _load_truth(args: argparse.Namespace):
    from livecap.demo import truth_path
    from livecap.demo.performance import GroundTruth

    path = Path(args.truth) if args.truth else truth_path(args.take)
    if not path.exists():
        if args.truth:
            raise OSError(f"{path}: no such ground-truth file")
        return None
    try:
        return GroundTruth.load(path)
    except (KeyError, ValueError) as exc:
        raise ValueError(f"{path}: not a ground-truth file ({exc})") from None


def _same_as(results) -> dict:
    """Variants whose solve equals an earlier variant's in every frame (to 1e-9) (e.g. plain Kabsch on a take where
    the robust stabiliser never needed its refit), by id: printed as one line naming the other, not as a copy."""
    out = {}
    for i, r in enumerate(results):
        for prev in results[:i]:
            if id(prev) not in out and np.allclose(r.solved.weights, prev.solved.weights, rtol=0, atol=1e-9) \
                    and np.allclose(r.solved.head_rotation, prev.solved.head_rotation, rtol=0, atol=1e-9):
                out[id(r)] = prev.variant.name
                break
    return out


def _stats(a: np.ndarray) -> str:
    return f"{np.mean(a):7.3f} {np.median(a):7.3f} {np.percentile(a, 95):7.3f} {np.max(a):7.3f}"


def run_report(args: argparse.Namespace) -> int:
    from livecap.modes.registry import build_solver
    from livecap.offline.calibration_report import compare, marker_residual, subsample

    rig, layout = load_rig(args)
    take = read_take(args.take)
    truth = _load_truth(args)
    prior = None
    if args.profile:
        loaded = Profile.load(args.profile)
        neutral, prior = loaded.source_neutral, loaded.prior
        origin = f"profile {args.profile}"
    elif args.neutral:
        neutral = estimate_neutral(read_take(args.neutral).select(layout.labels), layout.stable)
        origin = f"neutral take {args.neutral}"
    else:
        frames = max(1, int(args.neutral_seconds * take.rate))
        neutral = estimate_neutral(take.select(layout.labels), layout.stable, frames)
        origin = f"first {args.neutral_seconds:g} s of the take"
    stride = max(1, args.stride)
    take = subsample(take, stride)
    if truth is not None and stride > 1:
        truth = replace(truth, weights=truth.weights[::stride], head_rotation=truth.head_rotation[::stride],
                        head_translation=truth.head_translation[::stride])
    tuned: dict[int, dict] = {}

    resolved: list[str] = []

    def make_solver(p: Profile):  # each variant's profile tuned on the take for the modes that read the noise
        p.prior = p.prior or prior  # --profile's animation prior, as solve with that profile would use
        if id(p) not in tuned and args.mode == DEFAULT_MODE:  # auto reads the acting that tuning measures
            tuned[id(p)] = tune_on_take(p, take)
        mode = resolve_mode(args.mode, p)
        resolved.append(mode)
        if id(p) not in tuned and mode in ("movement", *ROBUST_MODES):
            tuned[id(p)] = tune_on_take(p, take)
        return build_solver(mode, p, {} if args.ridge is None else {"ridge": args.ridge})

    results = compare(take, rig, layout, neutral, make_solver, truth, progress=progress_bar)
    width = max(len(r.variant.name) for r in results)
    same = _same_as(results)
    mode = resolved[0] if resolved else args.mode
    print(f"take {args.take}: {take.n_frames} frames{f' (every {stride}th)' if stride > 1 else ''}, "
          f"{take.n_markers} markers, {(~take.valid).mean() * 100:.1f}% missing; neutral from {origin}; "
          f"mode {mode}" + (f" ridge {args.ridge:g}" if args.ridge is not None else ""))
    base = results[0]
    if truth is not None:
        print(f"\n{'per-frame weight error (RMS over shapes)':{width + 2}s}    mean  median     p95     max   RMSE  "
              "better  model@truth  systematic")
        for r in results:
            won = "" if r is base else f"{np.mean(base.frame_weight_error < r.frame_weight_error) * 100:5.0f}%"
            if id(r) in same:
                print(f"  {r.variant.name:{width}s} identical to '{same[id(r)]}' (no weight differs by 1e-9)")
                continue
            print(f"  {r.variant.name:{width}s} {_stats(r.frame_weight_error)} {r.weight_rmse:6.4f}  {won:>6s}"
                  f"  {r.model_error_mm:8.3f} mm  " + ("    n/a" if np.isnan(r.systematic_mm) else
                                                      f"{r.systematic_mm:7.3f} mm"))
        print("  (better: frames where the calibrated pipeline's weight error is lower; model@truth: RMS marker error"
              " of the\n   variant's model at the true weights; systematic: its part the true weights predict,"
              " i.e. calibration error)")
    print(f"\n{'per-frame marker fit of the solve (mm RMS)':{width + 2}s}    mean  median     p95     max")
    for r in results:
        if id(r) in same:
            print(f"  {r.variant.name:{width}s} identical to '{same[id(r)]}'")
            continue
        print(f"  {r.variant.name:{width}s} {_stats(r.frame_marker_error)}")
    rms, p95 = marker_residual(base)
    print(f"\nper-marker fit residual of '{base.variant.name}' (mm over the take, worst first)    RMS     p95")
    for j in np.argsort(-rms):
        print(f"  {base.profile.labels[j]:20s} {rms[j]:7.3f} {p95[j]:7.3f}")
    if truth is not None:
        print(f"\n{'head pose vs ground truth':{width + 17}s}    mean  median     p95     max")
        for r in results:
            if r.variant.stabilise == "off" or (r is not base and r.variant.stabilise == base.variant.stabilise):
                continue
            print(f"  {r.variant.name:{width}s} rotation (deg) {_stats(r.rotation_deg)}")
            print(f"  {'':{width}s} relative (deg) {_stats(r.relative_rotation_deg)}")
            print(f"  {'':{width}s} translation mm {_stats(r.translation_mm)}")
        dropped = ~take.select(layout.labels).valid[:, layout.stable].all(1)
        if dropped.any():
            print(f"  frames with a stable marker missing: {int(dropped.sum())}; calibrated rotation error there "
                  f"mean {base.rotation_deg[dropped].mean():.3f} max {base.rotation_deg[dropped].max():.3f} deg, "
                  f"translation mean {base.translation_mm[dropped].mean():.3f} max "
                  f"{base.translation_mm[dropped].max():.3f} mm")
    if args.per_frame:
        cols = ["frame", "time"]
        data = [take.first_frame + np.arange(take.n_frames), np.arange(take.n_frames) / take.rate]
        for i, r in enumerate(results):
            cols.append(f"marker_mm_{i}")
            data.append(r.frame_marker_error)
            if r.frame_weight_error is not None:
                cols.append(f"weight_err_{i}")
                data.append(r.frame_weight_error)
        header = ",".join(cols) + "\n# " + "; ".join(f"{i}: {r.variant.name}" for i, r in enumerate(results))
        np.savetxt(args.per_frame, np.column_stack(data), delimiter=",", header=header, comments="", fmt="%.6g")
        print(f"\nper-frame errors written to {args.per_frame}")
    return 0
