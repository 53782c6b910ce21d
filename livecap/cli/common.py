"""What several commands share: finding a rig's markers, calibrating, progress bars, reports."""

from __future__ import annotations

import argparse
from pathlib import Path

from livecap.calibration.profile import Profile, calibrate, check_layout_labels, check_rig_path, estimate_neutral
from livecap.cli import progress
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.core.take import Take


def markers_path(rig_path: str | Path) -> Path:
    """A rig's markers.json: inside an OBJ folder, or ``<rig>.markers.json`` beside a .npz."""
    p = Path(rig_path)
    return p / "markers.json" if p.is_dir() else p.with_name(p.stem + ".markers.json")


def load_rig(args: argparse.Namespace) -> tuple[Rig, MarkerLayout]:
    from transport.rig_files import load_rig as load_rig_file  # glTF/VRM/USD readers load only for their files

    rig = load_rig_file(args.rig)
    mpath = Path(args.markers) if getattr(args, "markers", None) else markers_path(args.rig)
    if not mpath.exists():
        raise ValueError(f"{mpath}: no markers.json for rig {args.rig} (give --markers)")
    return rig, MarkerLayout.load(mpath, rig)


def check_labels(take: Take, labels: list[str], take_path, rig_path) -> None:
    """A take that shares no marker label with the rig's ``labels`` is a wrong pairing, not a take with gaps: say so."""
    if not set(take.labels) & set(labels):
        raise ValueError(f"{take_path}: the take shares none of the {len(labels)} marker labels of rig {rig_path} "
                         f"(take: {', '.join(take.labels[:4])}...; rig: {', '.join(labels[:4])}...); give "
                         "a markers.json that binds the take's labels to the rig (--markers)")


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
    sel = take.select(layout.labels)
    with progress.stage("calibrating and tuning on the take (give --profile to skip)"):
        neutral = estimate_neutral(sel, layout.stable, max(1, int(args.neutral_seconds * take.rate)))
        profile = calibrate(rig, layout, neutral)
        tune_on_take(profile, take, getattr(args, "noise_mm", None))
    return profile


def saved_profile(args: argparse.Namespace, take: Take) -> Profile:
    """``--profile`` when nothing else needs the rig: the profile holds the calibrated basis and the marker
    labels, so the rig's meshes (seconds of OBJ parsing for a real rig) are not read; its path must exist."""
    if not Path(args.rig).exists():
        raise ValueError(f"{args.rig}: no such rig (an OBJ folder or .npz)")
    profile = Profile.load(args.profile)
    check_labels(take, profile.labels, getattr(args, "take", "take"), args.rig)
    mesh = check_rig_path(profile, args.rig, args.profile)
    if getattr(args, "markers", None):
        check_layout_labels(profile, args.markers, args.profile, mesh)
    return _given_noise(args, profile)


def tune_on_take(profile: Profile, take: Take, noise_mm: float | None = None) -> dict:
    from livecap.modes.robust import tune_profile
    from livecap.offline.solve import prepare_targets

    sel, targets, _, _ = prepare_targets(take, profile)
    return tune_profile(profile, targets, sel.valid, take.rate, noise_mm)


def solver_options(args: argparse.Namespace) -> dict:
    """Options common to every mode; unset flags are left out so modes keep their defaults."""
    ridge = getattr(args, "ridge", None)
    return {} if ridge is None else {"ridge": ridge}


progress_bar = progress.progress_bar  # kept here for the commands that import it from common
