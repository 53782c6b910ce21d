"""``livecap rom``: a synthetic range-of-motion take (each shape in turn) with labelled key ranges."""

from __future__ import annotations

import argparse
from pathlib import Path

from livecap.cli.common import load_rig
from livecap.demo import DEMO_RIG
from livecap.demo.performance import PerformanceSettings
from livecap.demo.rom import generate_rom

RECORDINGS = Path(__file__).resolve().parents[2] / "recordings"


def register(sub) -> None:
    p = sub.add_parser("rom", help="write a range-of-motion take and its labelled key ranges (keys JSON)",
                       description="The demo actor performs every shape of the rig in turn (Curio et al. 2006 "
                       "§2.1); writes <out>/demo_rom.c3d, its ground truth and demo_rom.keys.json.")
    p.add_argument("--rig", default=str(RECORDINGS / DEMO_RIG), help="rig (default: the bundled demo rig)")
    p.add_argument("--markers", help="markers.json (default: beside the rig)")
    p.add_argument("--out", default="out/rom", help="output folder (default out/rom)")
    p.add_argument("--seed", type=int, default=50, help="performance seed (noise, head motion)")
    p.add_argument("--rate", type=float, default=120.0)
    p.add_argument("--noise-mm", type=float, default=0.5)
    p.add_argument("--occlusion", type=float, default=0.02)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    rig, layout = load_rig(args)
    s = PerformanceSettings(rate=args.rate, noise_mm=args.noise_mm, occlusion=args.occlusion, seed=args.seed)
    for path in generate_rom(args.out, rig, layout, s):
        print(path)
    return 0
