"""``livecap map``: weight curves of one rig onto another (Lewis et al. 2014 §5.3)."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from livecap.offline.mapping import by_name, cloning_matrix, load_config
from transport.weights_csv import read_weights_csv, write_weights_csv


def register(sub) -> None:
    p = sub.add_parser("map", help="map weight curves to another rig: by name (gain/offset/clamp) or by a "
                       "linear cloning matrix fitted to pose pairs")
    p.add_argument("weights", help="source weights CSV (frame,time,<shape>...)")
    p.add_argument("--out", required=True, help="target weights CSV")
    p.add_argument("--target-rig", help="target rig (OBJ folder, .npz, glTF/VRM/USD file): its shape names are "
                   "the output channels")
    p.add_argument("--config", help="mapping config (.toml or .json): per-channel source, gain, offset, clamp")
    p.add_argument("--pairs", nargs=2, metavar=("SOURCE_POSES", "TARGET_POSES"),
                   help="two weights CSVs whose rows are corresponding poses: fit E (v = E w) and apply it")
    p.add_argument("--ridge", type=float, default=0.0,
                   help="ridge for the cloning fit, needed with fewer pairs than shapes (default 0)")
    p.add_argument("--allow-unmatched", action="store_true",
                   help="write the output even when most target channels have no source (default: error)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    names, W, times = read_weights_csv(args.weights)
    rate = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 and np.all(np.diff(times) > 0) else 1.0
    if args.pairs:
        src_names, Ws, _ = read_weights_csv(args.pairs[0])
        tgt_names, Vt, _ = read_weights_csv(args.pairs[1])
        if src_names != names:
            raise ValueError(f"{args.pairs[0]}: source pose channels differ from {args.weights}")
        E = cloning_matrix(Ws, Vt, args.ridge)
        out_names, V = tgt_names, W @ E.T
        print(f"cloning matrix {E.shape[0]} x {E.shape[1]} from {len(Ws)} pose pairs; "
              f"fit residual RMS {np.sqrt(np.mean((Ws @ E.T - Vt) ** 2)):.4g}")
    else:
        if args.target_rig:
            from transport.rig_files import load_rig

            out_names = list(load_rig(args.target_rig).names)
        else:
            out_names = list(names)
        cmap = by_name(names, out_names, load_config(args.config) if args.config else None)
        V = cmap.apply(W)
        report_unmatched(cmap, args)
    write_weights_csv(args.out, out_names, V, rate)
    print(f"{args.out}: {len(V)} frames x {len(out_names)} channels")
    return 0


def report_unmatched(cmap, args: argparse.Namespace) -> None:
    """Say which channels found no partner; most target channels unmatched is an error unless allowed."""
    n, k = len(cmap.unmapped), len(cmap.target_names)
    print(f"matched {k - n} of {k} target channels by name")
    if cmap.unmapped:
        print(f"target channels with no source ({n}, stay 0): {', '.join(cmap.unmapped)}")
    if cmap.unused:
        print(f"source channels not used ({len(cmap.unused)}): {', '.join(cmap.unused)}")
    if 2 * n > k:
        msg = (f"{args.weights}: {n} of {k} target channels have no source channel; name their sources in a "
               "--config mapping (docs/modes.md, 'Mapping between rigs')")
        if not args.allow_unmatched:
            raise ValueError(msg + " or pass --allow-unmatched")
        print(f"warning: {msg}", file=sys.stderr)
