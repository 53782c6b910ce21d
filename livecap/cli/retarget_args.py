"""How ARKit curves (a Live Link Face CSV or stream) reach a rig: by name, ``--map`` or ``--transfer``."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig

ICT_FOLDER = Path("realdata") / "ict-face"


def add_retarget_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("ARKit curves onto the rig (Live Link Face CSV or --livelink-in; docs/iphone.md)")
    how = g.add_mutually_exclusive_group()
    how.add_argument("--map", help="JSON mapping ARKit name -> rig shape name(s) for a rig whose names are not "
                     "ARKit's (e.g. examples/makehuman_arkit.json); default: by name")
    how.add_argument("--transfer", nargs="?", const="", metavar="ICT_RIG",
                     help="expression transfer: the curves drive the ICT-FaceKit face (folder; default "
                     "$LIVECAP_SHARED/realdata/ict-face or ../shared/realdata/ict-face), whose marker sites "
                     "the rig is solved from")


def _via_folder(given: str) -> Path:
    if given:
        return Path(given)
    roots = [Path(os.environ["LIVECAP_SHARED"])] if os.environ.get("LIVECAP_SHARED") else []
    roots.append(Path(__file__).resolve().parents[2].parent / "shared")
    for root in roots:
        if (root / ICT_FOLDER / "neutral.obj").exists():
            return root / ICT_FOLDER
    raise ValueError(f"--transfer: no ICT-FaceKit rig at {roots[-1] / ICT_FOLDER} (give its folder: --transfer DIR)")


def load_target(args: argparse.Namespace) -> tuple[Rig, MarkerLayout | None]:
    """``--rig`` and its markers when it has them (the name and map paths need none)."""
    from livecap.offline.setup import load_rig_layout, markers_path
    from transport.rig_files import load_rig

    if getattr(args, "markers", None) or markers_path(args.rig).exists():
        return load_rig_layout(args.rig, getattr(args, "markers", None))
    return load_rig(args.rig), None


def retargeter(args: argparse.Namespace, rig: Rig, layout: MarkerLayout | None):
    """By name, by ``--map``, or by expression transfer through the ICT face (livecap.retarget)."""
    from livecap.retarget import ByName, ExpressionTransfer

    if args.transfer is None:
        from transport.arkit import load_mapping

        return ByName(rig, load_mapping(args.map) if args.map else None, where=f"rig {args.rig}")
    from livecap.offline.setup import load_rig_layout

    via, via_layout = load_rig_layout(_via_folder(args.transfer))
    return ExpressionTransfer(via, via_layout, rig, layout)


def describe(args: argparse.Namespace) -> str:
    if args.transfer is not None:
        return "by expression transfer through the ICT face"
    return f"by the mapping {args.map}" if args.map else "by name"
