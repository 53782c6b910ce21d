"""``livecap pose``: solve rig weights that put pinned points of the face at given places.

Direct manipulation (Lewis & Anjyo 2010; Lewis et al. 2014 §5.5.2) for scripts: each --pin holds a
vertex (``VERTEX=X,Y,Z``) or a marker site (``marker:LABEL=X,Y,Z``) at a position in the rig frame
(mm); the weights inside the rig's limits that best do it, pulled towards the starting weights
(--from, default the neutral), are printed as CSV (shape,weight) or written with --out.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from livecap.cli.common import add_rig_arguments, load_rig
from solvers.manipulation import ManipulationSettings
from transport.weights_csv import read_weights_csv

if TYPE_CHECKING:
    from livecap.review.session import Pin


def register(sub) -> None:
    p = sub.add_parser("pose", help="solve weights that put pinned vertices/markers at given positions",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_rig_arguments(p)
    p.add_argument("--pin", action="append", required=True, metavar="VERTEX=X,Y,Z",
                   help="a pinned vertex (or marker:LABEL) and its goal in mm, rig frame (repeatable)")
    p.add_argument("--from", dest="start", metavar="W.CSV[:FRAME]",
                   help="starting weights: a weights CSV row (default frame 0); default the neutral")
    p.add_argument("--pull", type=float, default=1.0, help="pull towards the starting weights (default 1.0)")
    p.add_argument("--out", help="write shape,weight CSV here instead of stdout")
    p.set_defaults(func=run)


def parse_pin(text: str) -> Pin:
    from livecap.review.session import Pin

    who, sep, xyz = text.partition("=")
    try:
        goal = np.array([float(v) for v in xyz.split(",")])
    except ValueError:
        goal = np.zeros(0)
    if not sep or goal.shape != (3,):
        raise ValueError(f"--pin {text!r}: expected VERTEX=X,Y,Z or marker:LABEL=X,Y,Z")
    if who.startswith("marker:"):
        return Pin(goal, marker=who[len("marker:"):])
    try:
        return Pin(goal, vertex=int(who))
    except ValueError:
        raise ValueError(f"--pin {text!r}: {who!r} is not a vertex index (or marker:LABEL)") from None


def run(args: argparse.Namespace) -> int:
    from livecap.review.session import manipulator

    rig, layout = load_rig(args)
    pins = [parse_pin(p) for p in args.pin]
    current = np.zeros(rig.n_shapes)
    if args.start:
        path, _, frame = args.start.partition(":")
        if not Path(path).exists():
            raise FileNotFoundError(f"--from {path}: no such file")
        names, W, _ = read_weights_csv(path)
        row = W[int(frame or 0)]
        for n, v in zip(names, row, strict=True):
            if n in rig.names:
                current[rig.index(n)] = v
    dm = manipulator(rig, layout, pins, ManipulationSettings(pull=args.pull))
    start = time.perf_counter()
    w = dm.step(np.array([p.goal for p in pins]), current)
    ms = (time.perf_counter() - start) * 1e3
    text = "shape,weight\n" + "".join(f"{n},{v:.6g}\n" for n, v in zip(rig.names, w, strict=True))
    if args.out:
        Path(args.out).write_text(text)
        print(f"{args.out}: {len(pins)} pin(s), {rig.n_shapes} weights ({ms:.3f} ms)")
    else:
        sys.stdout.write(text)
    return 0
