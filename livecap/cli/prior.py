"""``livecap prior build``: a Gaussian prior on a rig's weights from real Live Link Face animation."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("prior", help="learn a prior on a rig's weights from real animation (Live Link Face CSVs)")
    psub = p.add_subparsers(dest="prior_command", metavar="ACTION", required=True)
    b = psub.add_parser("build", help="mean, full covariance and PCA subspace of the curves mapped onto --rig",
                        description="Lewis et al. 2014 §7.8-7.9; used by --mode kalman through --prior, its "
                                    "strength chosen on each take by held-out markers.")
    b.add_argument("curves", nargs="+", help="Live Link Face CSVs")
    b.add_argument("--rig", required=True, help="rig (folder, .npz, glTF/VRM/USD file) whose shapes the prior is over")
    b.add_argument("--mapping", help="ARKit name mapping JSON for rigs whose names are not ARKit's")
    b.add_argument("--out", required=True, help="prior .npz to write")
    b.set_defaults(func=run_build)


def run_build(args: argparse.Namespace) -> int:
    from livecap.calibration.animation_prior import build_prior
    from transport.arkit import load_mapping
    from transport.rig_files import load_rig

    rig = load_rig(args.rig)
    mapping = load_mapping(args.mapping) if args.mapping else None
    prior = build_prior(args.curves, rig.names, rig.lower, rig.upper, mapping)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    prior.save(args.out)
    axes, var = prior.pca()
    print(f"{args.out}: {prior.frames} frames from {len(args.curves)} files, {rig.n_shapes} shapes; "
          f"PCA keeps {axes.shape[1]} axes for 99 % of the variance")
    return 0
