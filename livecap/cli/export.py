"""``livecap export``: solved weight curves (CSV) and their rig as one glTF 2.0 binary (.glb)."""

from __future__ import annotations

import argparse
from pathlib import Path

from transport.rig_files import load_rig
from transport.weights_csv import read_weights_csv


def register(sub) -> None:
    p = sub.add_parser("export", help="weights CSV + rig -> glTF 2.0 (.glb) with morph targets and animation",
                       description="Write a solved take as .glb: the rig's neutral mesh, one morph target per "
                                   "shape and an animation of the weight curves (head pose: use 'livecap solve "
                                   "--out take.glb').")
    p.add_argument("weights", help="weights CSV from 'livecap solve' (frame,time,<shape>...)")
    p.add_argument("--rig", required=True, help="rig: OBJ folder, .npz, glTF/GLB, VRM or USD (docs/rigs.md)")
    p.add_argument("--out", required=True, help="output .glb")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if Path(args.out).suffix.lower() != ".glb":
        raise ValueError(f"--out {args.out}: export writes .glb")
    from transport.gltf import write_glb  # pygltflib: not for every livecap command

    rig = load_rig(args.rig)
    names, weights, times = read_weights_csv(args.weights)
    write_glb(args.out, rig, names, times, weights)
    print(f"{args.out}: {len(times)} frames x {len(names)} shapes, {rig.n_vertices} vertices")
    return 0
