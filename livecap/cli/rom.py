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
    p = sub.add_parser("rom", help="write a range-of-motion take of a rig and its labelled key ranges (keys JSON)",
                       description="A synthetic actor performs every shape of the rig in turn (Curio et al. 2006 "
                       "§2.1): one second of neutral face, then each shape up, held, down. Writes <out>/<name>.c3d, "
                       "its ground truth (<name>.truth.npz) and <name>.keys.json: a neutral take for "
                       "'livecap calibrate --seconds 1', a tuning take for --tune, and the keys for "
                       "'--mode rbf' / '--basis actor' (docs/quickstart.md).")
    p.add_argument("--rig", default=str(RECORDINGS / DEMO_RIG), help="rig: OBJ folder or .npz (default: the bundled "
                   "demo rig)")
    p.add_argument("--markers", help="markers.json (default: beside the rig)")
    p.add_argument("--out", default="out/rom", help="output folder (default out/rom)")
    p.add_argument("--name", help="file name stem (default: demo_rom for the bundled rig, else <rig name>_rom)")
    p.add_argument("--seed", type=int, default=50, help="performance seed: noise, head motion (default 50)")
    p.add_argument("--rate", type=float, default=120.0, help="frame rate in Hz (default 120)")
    p.add_argument("--noise-mm", type=float, default=0.5, help="marker noise sigma in mm (default 0.5)")
    p.add_argument("--occlusion", type=float, default=0.02, help="fraction of marker-frames missing (default 0.02)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    rig, layout = load_rig(args)
    s = PerformanceSettings(rate=args.rate, noise_mm=args.noise_mm, occlusion=args.occlusion, seed=args.seed)
    name = args.name or ("demo_rom" if Path(args.rig).resolve() == (RECORDINGS / DEMO_RIG).resolve()
                         else f"{Path(args.rig).stem}_rom")
    for path in generate_rom(args.out, rig, layout, s, name):
        print(path)
    return 0
