"""``livecap edit``: spacetime edits of solved weight curves (Seol et al. 2012 §6).

An edit sets some weights at a frame; its influence spreads over a propagation range [a, b]
(a and b keep their values) by re-solving movement matching inside the range with the edit as a
boundary condition. With ``--take`` and ``--rig`` the movement to keep is the source markers'
(Seol); without them it is the current curves' own movement, so the correction spreads linearly.
"""

from __future__ import annotations

import argparse
import json
import re
import time
from pathlib import Path

import numpy as np

from livecap.cli.common import add_calibration_arguments, load_rig, profile_for
from livecap.cli.movement_args import add_movement_arguments, movement_options
from livecap.modes.movement import build_movement
from livecap.offline.solve import prepare_targets
from solvers.movement import Edit, MovementMatching
from transport.takefile import read_take
from transport.weights_csv import read_weights_csv, write_weights_csv

INLINE = re.compile(r"^(?P<frame>-?\d+):(?P<sets>[^@]*)(@(?P<a>-?\d+)[-:](?P<b>-?\d+))?$")


def register(sub) -> None:
    p = sub.add_parser("edit", help="spacetime-edit a weights CSV: set weights at a frame, propagate over a range",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("weights", help="weights CSV (frame,time,<shape>...) to edit")
    p.add_argument("--edits", help='JSON edit list: [{"frame": 68, "weights": {"jawOpen": 0.8}, "range": [63, 74]}]')
    p.add_argument("--edit", action="append", default=[], metavar="FRAME:NAME=V[,NAME=V][@A-B]",
                   help="one inline edit, e.g. 68:jawOpen=0.8,mouthSmileLeft=0.3@63-74 (repeatable)")
    p.add_argument("--out", required=True, help="edited weights CSV")
    p.add_argument("--take", help="the source take the weights were solved from (keeps its movement)")
    p.add_argument("--rig", help="rig (OBJ folder, .npz, glTF/GLB, VRM or USD); needed with --take")
    p.add_argument("--markers", help="markers.json (default: beside the rig)")
    add_calibration_arguments(p)
    add_movement_arguments(p, stream=False)
    p.set_defaults(func=run)


def parse_edits(args: argparse.Namespace, names: list[str], first_frame: int, n_frames: int) -> list[Edit]:
    """Edits from --edits (JSON) and --edit (inline), frames in the CSV's numbering."""
    raw: list[dict] = []
    if args.edits:
        try:
            data = json.loads(Path(args.edits).read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{args.edits}: not valid JSON ({exc})") from None
        raw += data["edits"] if isinstance(data, dict) else data
    for item in args.edit:
        mt = INLINE.match(item.replace(" ", ""))
        if not mt:
            raise ValueError(f"--edit {item!r}: expected FRAME:NAME=VALUE[,NAME=VALUE][@A-B]")
        sets = {}
        for kv in filter(None, mt["sets"].split(",")):
            k, sep, v = kv.partition("=")
            if not sep:
                raise ValueError(f"--edit {item!r}: {kv!r} is not NAME=VALUE")
            sets[k] = float(v)
        raw.append({"frame": int(mt["frame"]), "weights": sets,
                    "range": [int(mt["a"]), int(mt["b"])] if mt["a"] is not None else None})
    if not raw:
        raise ValueError("no edits given (use --edits FILE or --edit ...)")
    index = {n: j for j, n in enumerate(names)}
    edits = []
    for e in raw:
        unknown = [k for k in e.get("weights", {}) if k not in index]
        if unknown:
            raise ValueError(f"edit at frame {e.get('frame')}: unknown shapes {unknown[:5]}")
        k = int(e["frame"]) - first_frame
        rng = e.get("range")
        rng = None if rng is None else (int(rng[0]) - first_frame, int(rng[1]) - first_frame)
        if not 0 <= k < n_frames:
            last = first_frame + n_frames - 1
            raise ValueError(f"edit frame {e['frame']} is outside the curves ({first_frame}..{last})")
        edits.append(Edit(k, {index[n]: float(v) for n, v in e.get("weights", {}).items()}, rng))
    return edits


def _frames(path: str) -> np.ndarray:
    return np.atleast_1d(np.loadtxt(path, delimiter=",", skiprows=1, usecols=0, ndmin=1)).astype(int)


def run(args: argparse.Namespace) -> int:
    names, W, times = read_weights_csv(args.weights)
    frames = _frames(args.weights)
    rate = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else 1.0
    if args.take:
        if not args.rig:
            raise ValueError("--take needs --rig")
        rig, layout = load_rig(args)
        take = read_take(args.take)
        if take.n_frames != len(W):
            raise ValueError(f"{args.take}: {take.n_frames} frames but {args.weights} has {len(W)} rows")
        profile = profile_for(args, rig, layout, take)
        missing = sorted(set(profile.names) - set(names))
        if missing:
            raise ValueError(f"{args.weights}: no column for rig shapes {missing[:5]}")
        order = [names.index(n) for n in profile.names]
        solver = build_movement(profile, movement_options(args))
        _, targets, _, _ = prepare_targets(take, profile)
        edits = parse_edits(args, profile.names, int(frames[0]), len(W))
        start = time.perf_counter()
        E = solver.edit(W[:, order], edits, targets, take.select(profile.labels).valid)
        out = W.copy()
        out[:, order] = E
    else:  # the curves' own movement in weight space
        m = len(names)
        basis = np.zeros((3 * m, m))  # each weight as the x of one pseudo-marker
        basis[3 * np.arange(m), np.arange(m)] = 1.0
        solver = MovementMatching(basis)
        edits = parse_edits(args, names, int(frames[0]), len(W))
        start = time.perf_counter()
        out = solver.edit(W, edits, np.stack([W, np.zeros_like(W), np.zeros_like(W)], axis=2))
    elapsed = time.perf_counter() - start
    write_weights_csv(args.out, names, out, rate, int(frames[0]))
    changed = np.flatnonzero(np.any(out != W, axis=1))
    span = f"frames {frames[changed[0]]}..{frames[changed[-1]]}" if len(changed) else "no frame"
    print(f"{args.out}: {len(edits)} edit(s), {span} changed ({elapsed * 1e3:.2f} ms)")
    return 0
