"""``livecap markers``: marker layouts. ``livecap markers bind`` binds a real capture's markers to a rig.

The work is :func:`livecap.transfer.bind.bind_capture`; see docs/transfer.md (Binding a capture).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from livecap.cli.common import command_group, markers_path, parse_span
from transport.rig_files import RIG_FILES_HELP


def register(sub) -> None:
    msub = command_group(sub, "markers", "marker layouts (bind a capture's markers to a rig)")
    b = msub.add_parser(
        "bind", help="place every marker of a capture on a rig's surface (writes markers.json)",
        description="From a near-neutral span of a capture and the rig alone, bind each marker to a triangle of the "
                    "rig (skin offset allowed), choose the stable markers by rigidity over the take, and report per "
                    "marker its distance to the surface and stability; markers off the rig's face are left out.")
    b.add_argument("take", help="capture take (.c3d, .trc, .csv ...) holding a near-neutral span")
    b.add_argument("--rig", required=True, help=f"rig: {RIG_FILES_HELP}")
    b.add_argument("--mesh", help="the face mesh of a glTF/VRM/USD rig when the file holds several (as livecap rig "
                   "import takes it)")
    b.add_argument("--rig-markers", help="the rig's markers.json (landmarks for name hints; default: in the rig "
                   "folder or <rig>.markers.json beside the file; without one, geometry only)")
    b.add_argument("--out", required=True, help="markers.json to write")
    b.add_argument("--span", metavar="START:END", help="near-neutral span in seconds (default: auto-detected)")
    b.add_argument("--rom", metavar="TAKE", help="range-of-motion take of the same markers: measure rigidity (the "
                   "stable set) there instead of over TAKE")
    b.add_argument("--no-names", action="store_true", help="ignore marker names (geometry only)")
    b.set_defaults(func=run_bind)


def run_bind(args: argparse.Namespace) -> int:
    from livecap.core.markers import MarkerLayout
    from livecap.transfer.bind import BindOptions, bind_capture
    from transport.rig_files import load_rig
    from transport.takefile import read_take

    take = read_take(args.take)
    rig = load_rig(args.rig, args.mesh)
    mpath = Path(args.rig_markers) if args.rig_markers else markers_path(args.rig)
    layout = MarkerLayout.load(mpath, rig) if mpath.exists() else None
    span = parse_span(args.span, take.rate, take.n_frames) if args.span else None
    rom = read_take(args.rom) if args.rom else None
    res = bind_capture(take, rig, layout, span, BindOptions(use_names=not args.no_names), rom)
    s0, s1 = res.span
    print(f"neutral span {s0 / take.rate:.2f}-{s1 / take.rate:.2f} s; actor -> rig scale {res.alignment.scale:.3f}; "
          f"RMS marker-surface distance {res.rms:.2f} mm; start from "
          + (f"{len(res.anchors)} name hints" if res.anchors else "geometry only"))
    print(f"{'marker':<18}{'distance mm':>12}{'stability mm':>14}  stable")
    for m in res.markers:
        note = "yes" if m.stable else ""
        if not m.bound:
            note = f"NOT BOUND: {m.reason}"
        print(f"{m.label:<18}{m.distance:>12.2f}{m.stability:>14.2f}  {note}")
    bound = res.layout(rig)
    if not bound.n_markers:
        raise ValueError(f"{args.take}: no marker could be bound to {args.rig}")
    extra = {m.label: {"distance_mm": round(m.distance, 3), "stability_mm": round(m.stability, 3)}
             for m in res.markers if m.bound}
    bound.save(args.out, rig, extra)
    print(f"wrote {args.out}: {bound.n_markers} of {len(res.markers)} markers bound, "
          f"{int(bound.stable.sum())} stable")
    return 0
