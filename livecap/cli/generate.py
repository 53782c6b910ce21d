"""``livecap generate``: the procedural demo rig and synthetic takes with ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from livecap.demo import generate
from livecap.demo.performance import PerformanceSettings


def register(sub) -> None:
    p = sub.add_parser("generate", help="write the procedural demo rig, markers and synthetic takes")
    p.add_argument("--out", default="recordings", help="output folder (default recordings/)")
    p.add_argument("--seed", type=int, default=0, help="rig seed; the performance uses seed + 1")
    p.add_argument("--seconds", type=float, default=20.0, help="length of the performance take (default 20)")
    p.add_argument("--rate", type=float, default=120.0, help="frame rate in Hz (default 120)")
    p.add_argument("--noise-mm", type=float, default=0.5, help="marker noise sigma in mm")
    p.add_argument("--occlusion", type=float, default=0.02, help="fraction of marker-frames missing")
    p.add_argument("--head-degrees", type=float, default=20.0, help="head rotation amplitude (default 20)")
    p.add_argument("--head-mm", type=float, default=30.0, help="head translation amplitude in mm (default 30)")
    p.add_argument("--obj-rig", metavar="DIR", help="also write the rig as an OBJ folder (neutral.obj, one OBJ per "
                   "shape, rig.json, markers.json): the layout your own rig needs (docs/quickstart.md)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    s = PerformanceSettings(seconds=args.seconds, rate=args.rate, noise_mm=args.noise_mm,
                            occlusion=args.occlusion, head_degrees=args.head_degrees, head_mm=args.head_mm,
                            seed=args.seed + 1)
    for path in generate(args.out, args.seed, s):
        print(path)
    if args.obj_rig:
        from livecap.demo.face import demo_rig

        rig, layout = demo_rig(args.seed)
        rig.save_obj_folder(args.obj_rig)
        layout.save(Path(args.obj_rig) / "markers.json")
        print(f"{args.obj_rig}/: neutral.obj + {rig.n_shapes} shape OBJs, rig.json, markers.json")
    return 0
