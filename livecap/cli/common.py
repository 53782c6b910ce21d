"""What several commands share: finding a rig's markers, calibrating, progress bars, reports."""

from __future__ import annotations

import argparse

from livecap.calibration.profile import Profile
from livecap.cli import progress
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.core.take import Take
from livecap.offline.setup import (
    check_labels,
    check_profile_for_rig,
    load_rig_layout,
    markers_path,
    profile_from_take,
    tune_on_take,
)

__all__ = ["check_labels", "markers_path", "tune_on_take"]  # kept here for the commands that import them


def load_rig(args: argparse.Namespace) -> tuple[Rig, MarkerLayout]:
    return load_rig_layout(args.rig, getattr(args, "markers", None))


def command_group(sub, name: str, help: str):
    """A command with subcommands (``livecap rig import``, ``livecap markers bind``): the subparsers to add them
    to; the command alone prints its help and exits 2."""
    p = sub.add_parser(name, help=help)
    p.set_defaults(func=lambda args: p.print_help() or 2)
    return p.add_subparsers(dest=f"{name}_command", metavar=f"{name.upper()}_COMMAND")


def add_rig_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", required=True, help="rig: OBJ folder (neutral.obj + one OBJ per shape), .npz, "
                   "glTF/GLB, VRM or USD (docs/rigs.md)")
    p.add_argument("--markers", help="markers.json (default: in the rig folder, or <rig>.markers.json)")


def add_take_solve_arguments(p: argparse.ArgumentParser) -> None:
    """A take, its rig, calibration and the solver mode: what every take-solving command takes."""
    from livecap.modes.registry import DEFAULT_MODE, MODE_HELP, MODES_AND_AUTO

    p.add_argument("take", help="marker take: .c3d, .trc or .csv")
    add_rig_arguments(p)
    add_calibration_arguments(p)
    p.add_argument("--mode", default=DEFAULT_MODE, choices=sorted(MODES_AND_AUTO), help=MODE_HELP)
    p.add_argument("--ridge", type=float,
                   help="ridge weight lambda (default: the mode's, or the one calibration selected)")
    add_noise_argument(p)


def add_noise_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--noise-mm", type=float, help="marker noise sigma per coordinate, mm, that the solvers must "
                   "not explain (default: what calibration measured: jitter and the rig's fit residual; "
                   "docs/calibration.md)")


def _given_noise(args: argparse.Namespace, profile: Profile) -> Profile:
    if getattr(args, "noise_mm", None) is not None:
        from livecap.modes.robust import override_noise

        override_noise(profile, args.noise_mm)
    return profile


def add_calibration_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--profile", help="calibrated profile (.npz from 'livecap calibrate'); "
                   "without it the take's first --neutral-seconds are taken as the neutral face")
    p.add_argument("--neutral-seconds", type=float, default=1.0,
                   help="neutral span at the start of the take when no --profile (default 1.0)")


def profile_for(args: argparse.Namespace, rig: Rig, layout: MarkerLayout, take: Take) -> Profile:
    """The given profile, or one calibrated on the take's first seconds with its regularisation
    selected from the take itself (livecap.modes.robust.tune_profile)."""
    check_labels(take, layout.labels, getattr(args, "take", "take"), args.rig)
    if getattr(args, "profile", None):
        return _given_noise(args, Profile.load(args.profile))
    with progress.stage("calibrating and tuning on the take (give --profile to skip)"):
        return profile_from_take(rig, layout, take, args.neutral_seconds, getattr(args, "noise_mm", None))


def saved_profile(args: argparse.Namespace, take: Take) -> Profile:
    """``--profile`` when nothing else needs the rig: the profile holds the calibrated basis and the marker
    labels, so the rig's meshes (seconds of OBJ parsing for a real rig) are not read; its path must exist."""
    profile = Profile.load(args.profile)
    check_labels(take, profile.labels, getattr(args, "take", "take"), args.rig)
    check_profile_for_rig(profile, args.rig, args.profile, getattr(args, "markers", None))
    return _given_noise(args, profile)


def parse_span(text: str, rate: float, n_frames: int) -> tuple[int, int]:
    """'START:END' seconds -> frames (start, stop), checked against the take."""
    try:
        a, b = (float(x) for x in text.split(":"))
    except ValueError:
        raise ValueError(f"--span: expected START:END in seconds, got {text!r}") from None
    start, stop = int(round(a * rate)), int(round(b * rate))
    if not 0 <= start < stop <= n_frames:
        raise ValueError(f"--span {text}: outside the take's 0:{n_frames / rate:g} s or empty")
    return start, stop


def solver_options(args: argparse.Namespace) -> dict:
    """Options common to every mode; unset flags are left out so modes keep their defaults."""
    ridge = getattr(args, "ridge", None)
    return {} if ridge is None else {"ridge": ridge}


progress_bar = progress.progress_bar  # kept here for the commands that import it from common
