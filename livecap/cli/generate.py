"""``livecap generate``: the procedural demo rig and synthetic takes with ground truth; with
``--curves``, a take of any rig driven by a real Live Link Face performance (issue 15)."""

from __future__ import annotations

import argparse
from dataclasses import fields
from pathlib import Path

from livecap.demo import generate
from livecap.demo.performance import PerformanceSettings


def register(sub) -> None:
    p = sub.add_parser("generate", help="write the procedural demo rig, markers and synthetic takes, "
                       "or (--curves) a take of a rig driven by real Live Link Face curves")
    p.add_argument("--out", default="recordings", help="output folder (default recordings/)")
    p.add_argument("--seed", type=int, default=0, help="rig seed; the performance uses seed + 1")
    p.add_argument("--seconds", type=float, help="take length (default 20; with --curves: the whole CSV)")
    p.add_argument("--rate", type=float, help="frame rate (default 120; with --curves 60, the CSV's timecode rate)")
    p.add_argument("--noise-mm", type=float, default=0.5, help="marker noise sigma in mm")
    p.add_argument("--occlusion", type=float, help="fraction of marker-frames missing (default 0.02; "
                   "with --curves 0.05)")
    p.add_argument("--head-degrees", type=float, help="head rotation amplitude (default 20; with --curves 15)")
    p.add_argument("--head-mm", type=float, help="head shift amplitude (default 30; with --curves 20)")
    p.add_argument("--obj-rig", metavar="DIR", help="also write the rig as an OBJ folder (neutral.obj, one OBJ per "
                   "shape, rig.json, markers.json): the layout your own rig needs (docs/quickstart.md)")
    c = p.add_argument_group("real curves")
    c.add_argument("--curves", help="Live Link Face CSV whose ARKit curves drive --rig")
    c.add_argument("--rig", help="rig (OBJ folder, .npz, glTF/GLB, VRM or USD) to drive "
                   "(default: the bundled demo rig)")
    c.add_argument("--markers", help="markers.json (default: beside the rig)")
    c.add_argument("--mapping", help="JSON {ARKit name: rig shape | [shapes]} for rigs whose names are not ARKit's")
    c.add_argument("--start", type=float, default=0.0, help="seconds into the CSV")
    c.add_argument("--actor-seed", type=int, default=7, help="the actor's proportions (same seed, same face)")
    a = p.add_argument_group("model mismatch (--curves with --actor-rig)")
    a.add_argument("--actor-rig", metavar="RIG", help="the actor is this other rig (e.g. the MakeHuman head) driven by "
                   "--curves through --mapping; its markers, placed like --rig's and bound to --rig as "
                   "'livecap markers bind' does, go to OUT/<curves>.markers.json; truth: what the actor did on --rig's "
                   "names (names its mapping has no shape for at rest), the curves beside it")
    a.add_argument("--skin-offset", default="2:5", metavar="MIN:MAX", help="markers off the actor's skin, mm (2:5)")
    a.add_argument("--placement-mm", type=float, default=2.0, help="marker placement error, +- mm (default 2)")
    a.add_argument("--smoothing-hz", type=float, default=6.0,
                   help="the capture pipeline's low-pass cut-off in Hz (default 6; 0 = none)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.actor_rig:
        if not args.curves or not args.rig:
            raise ValueError("--actor-rig needs --curves and --rig (the target rig)")
        return run_mismatch(args)
    if args.curves:
        return run_curves(args)
    s = PerformanceSettings(seconds=args.seconds or 20.0, rate=args.rate or 120.0, noise_mm=args.noise_mm,
                            occlusion=0.02 if args.occlusion is None else args.occlusion,
                            head_degrees=20.0 if args.head_degrees is None else args.head_degrees,
                            head_mm=30.0 if args.head_mm is None else args.head_mm, seed=args.seed + 1)
    for path in generate(args.out, args.seed, s):
        print(path)
    if args.obj_rig:
        from livecap.demo.face import demo_rig

        rig, layout = demo_rig(args.seed)
        rig.save_obj_folder(args.obj_rig)
        layout.save(Path(args.obj_rig) / "markers.json")
        print(f"{args.obj_rig}/: neutral.obj + {rig.n_shapes} shape OBJs, rig.json, markers.json")
    return 0


def run_curves(args: argparse.Namespace) -> int:
    from livecap.cli.common import load_rig
    from livecap.demo import DEMO_RIG, truth_path
    from livecap.demo.curves_take import CurveTakeSettings, curves_take
    from transport.arkit import load_mapping
    from transport.takefile import write_take

    if not args.rig:
        args.rig = str(Path(__file__).resolve().parents[2] / "recordings" / DEMO_RIG)
    rig, layout = load_rig(args)
    given = {"rate": args.rate, "seconds": args.seconds, "occlusion": args.occlusion,
             "head_degrees": args.head_degrees, "head_mm": args.head_mm}
    known = {f.name for f in fields(CurveTakeSettings)}
    s = CurveTakeSettings(**{k: v for k, v in given.items() if v is not None and k in known},
                          noise_mm=args.noise_mm, start=args.start, seed=args.seed + 1, actor_seed=args.actor_seed)
    mapping = load_mapping(args.mapping) if args.mapping else None
    ct = curves_take(rig, layout, args.curves, s, mapping)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = Path(args.curves).stem
    take_path, neutral_path = out / f"{stem}.c3d", out / f"{stem}_neutral.c3d"
    write_take(ct.take, take_path)
    ct.save_truth(truth_path(take_path))
    write_take(ct.neutral, neutral_path)
    active = float((ct.weights > 0.05).sum(1).mean())
    print(f"{take_path}: {ct.take.n_frames} frames at {s.rate:g} Hz, {active:.1f} of {rig.n_shapes} shapes "
          f"above 0.05 per frame, {(~ct.take.valid).mean() * 100:.1f}% missing")
    if ct.unmapped:
        print(f"rig shapes no ARKit curve drives (held at 0): {', '.join(ct.unmapped)}")
    for path in (truth_path(take_path), neutral_path):
        print(path)
    return 0


def run_mismatch(args: argparse.Namespace) -> int:
    import numpy as np

    from livecap.cli.common import load_rig
    from livecap.demo import truth_path
    from livecap.demo.mismatch_take import MismatchSettings, mismatch_take
    from transport.arkit import load_mapping
    from transport.rig_files import load_rig as load_rig_file
    from transport.takefile import write_take

    try:
        lo, hi = (float(x) for x in args.skin_offset.split(":"))
    except ValueError:
        raise ValueError(f"--skin-offset: expected MIN:MAX in mm, got {args.skin_offset!r}") from None
    target, layout = load_rig(args)
    actor = load_rig_file(args.actor_rig)
    given = {"rate": args.rate, "seconds": args.seconds, "occlusion": args.occlusion,
             "head_degrees": args.head_degrees, "head_mm": args.head_mm}
    s = MismatchSettings(**{k: v for k, v in given.items() if v is not None}, start=args.start, seed=args.seed + 1,
                         noise_mm=args.noise_mm, skin_offset_mm=(lo, hi), placement_mm=args.placement_mm,
                         smoothing_hz=args.smoothing_hz)
    mt = mismatch_take(actor, target, layout, args.curves, load_mapping(args.mapping) if args.mapping else None, s)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = Path(args.curves).stem
    take_path, neutral_path, markers = out / f"{stem}.c3d", out / f"{stem}_neutral.c3d", out / f"{stem}.markers.json"
    write_take(mt.take, take_path)
    mt.save_truth(truth_path(take_path))
    write_take(mt.neutral, neutral_path)
    mt.layout.save(markers, target, {m.label: {"distance_mm": round(m.distance, 3)} for m in mt.binding.markers
                                     if m.bound})
    d = [m.distance for m in mt.binding.markers if m.bound]
    print(f"{take_path}: {mt.take.n_frames} frames at {s.rate:g} Hz, actor {args.actor_rig}, "
          f"{(~mt.take.valid).mean() * 100:.1f}% missing; {markers}: {mt.layout.n_markers} of "
          f"{mt.take.n_markers} markers bound to {args.rig} (median {np.median(d):.1f} mm off its surface)")
    for path in (truth_path(take_path), neutral_path):
        print(path)
    return 0
