"""``livecap info``: describe a rig or a take."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from livecap.cli.common import markers_path
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from transport.rig_files import load_rig
from transport.takefile import READERS, read_take


def register(sub) -> None:
    p = sub.add_parser("info", help="describe a rig (OBJ folder, .npz, glTF/GLB, VRM, USD) or a take (.c3d/.trc/.csv)")
    p.add_argument("path")
    p.add_argument("--markers", help="markers.json for a rig (default: found beside it)")
    p.add_argument("--observability", action="store_true",
                   help="for a rig + markers or a --profile: which shapes the markers can see (docs/robustness.md)")
    p.add_argument("--profile", help="with --observability: a calibrated profile (.npz) instead of the raw rig basis")
    p.add_argument("--noise-mm", type=float, default=None,
                   help="marker noise sigma for the report (default: the profile's estimate, else 0.5)")
    p.set_defaults(func=run)


def observability_report(args: argparse.Namespace, rig: Rig | None, layout: MarkerLayout | None) -> None:
    from livecap.calibration.profile import Profile
    from solvers.observability import observability

    per_marker = None
    if args.profile:
        from livecap.modes.quiet import marker_noise

        prof = Profile.load(args.profile)
        basis, names, per_marker = prof.basis, prof.names, marker_noise(prof)
        noise = args.noise_mm or prof.settings.get("robust", {}).get("noise_mm", 0.5)
        source = args.profile
    else:
        if layout is None:
            raise ValueError(f"{args.path}: --observability needs the rig's markers.json (give --markers)")
        basis, names, noise, source = layout.basis(rig), rig.names, args.noise_mm or 0.5, "rig + markers"
    print(f"  ({source})")
    for line in observability(basis, names, noise, marker_noise=per_marker).lines():
        print(line)


def run(args: argparse.Namespace) -> int:
    path = Path(args.path)
    if args.observability and args.profile and not path.exists():
        observability_report(args, None, None)
        return 0
    if path.suffix.lower() in READERS:
        take = read_take(path)
        missing = (~take.valid).mean(0)
        print(f"take {path}: {take.n_frames} frames at {take.rate:g} Hz ({take.duration:.2f} s), "
              f"{take.n_markers} markers, first frame {take.first_frame}")
        print(f"  missing: {(~take.valid).mean() * 100:.2f}% of marker-frames; worst "
              + ", ".join(f"{take.labels[i]} {missing[i] * 100:.1f}%" for i in np.argsort(-missing)[:3]))
        lo = take.positions[take.valid].min(0)
        hi = take.positions[take.valid].max(0)
        print(f"  extent (mm): {np.round(lo, 1).tolist()} .. {np.round(hi, 1).tolist()}")
        return 0
    rig = load_rig(path)
    ext = np.ptp(rig.neutral, axis=0)
    print(f"rig {path}: {rig.n_vertices} vertices, {len(rig.triangles)} triangles, {rig.n_shapes} shapes, "
          f"{len(rig.inbetweens)} in-betweens, {len(rig.correctives)} correctives")
    print(f"  extent (mm): {np.round(ext, 1).tolist()}")
    mags = np.linalg.norm(rig.deltas, axis=2).max(axis=1)
    for name, lo, hi, mag in zip(rig.names, rig.lower, rig.upper, mags, strict=True):
        print(f"  {name:24s} [{lo:g}, {hi:g}]  max displacement {mag:6.2f} mm")
    mpath = Path(args.markers) if args.markers else markers_path(path)
    layout = None
    if mpath.exists():
        layout = MarkerLayout.load(mpath, rig)
        print(f"  markers: {layout.n_markers} ({int(layout.stable.sum())} stable: "
              f"{', '.join(layout.stable_labels())}) from {mpath}")
    if args.observability:
        observability_report(args, rig, layout)
    return 0
