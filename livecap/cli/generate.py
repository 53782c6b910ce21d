"""``livecap generate``: the procedural demo rig and synthetic takes with ground truth."""

from __future__ import annotations

import argparse

from livecap.demo import generate
from livecap.demo.performance import PerformanceSettings


def register(sub) -> None:
    p = sub.add_parser("generate", help="write the procedural demo rig, markers and synthetic takes")
    p.add_argument("--out", default="recordings", help="output folder (default recordings/)")
    p.add_argument("--seed", type=int, default=0, help="rig seed; the performance uses seed + 1")
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--rate", type=float, default=120.0)
    p.add_argument("--noise-mm", type=float, default=0.5, help="marker noise sigma in mm")
    p.add_argument("--occlusion", type=float, default=0.02, help="fraction of marker-frames missing")
    p.add_argument("--head-degrees", type=float, default=20.0)
    p.add_argument("--head-mm", type=float, default=30.0)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    s = PerformanceSettings(seconds=args.seconds, rate=args.rate, noise_mm=args.noise_mm,
                            occlusion=args.occlusion, head_degrees=args.head_degrees, head_mm=args.head_mm,
                            seed=args.seed + 1)
    for path in generate(args.out, args.seed, s):
        print(path)
    return 0
