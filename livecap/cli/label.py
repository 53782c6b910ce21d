"""``livecap label``: a take of unlabelled (``*12``-style) or wrongly named points in, the same
take with the profile's labels out (C3D, TRC or CSV by extension)."""

from __future__ import annotations

import argparse

from livecap.calibration.profile import Profile
from livecap.core.take import Take


def register(sub) -> None:
    p = sub.add_parser("label", help="label a take of unlabelled marker points against a calibrated profile",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("take", help="marker take: .c3d, .trc or .csv (point names are ignored)")
    p.add_argument("--profile", required=True, help="calibrated profile (.npz from 'livecap calibrate')")
    p.add_argument("--out", required=True, help="labelled take: .c3d, .trc or .csv")
    p.set_defaults(func=run)


def labelled_take(args: argparse.Namespace, take: Take) -> Take:
    """The take labelled against ``args.profile`` (which must be given); prints what was found."""
    from livecap.live.unlabelled import label_take, labeller_for

    if not getattr(args, "profile", None):
        raise ValueError("--unlabelled needs --profile: labels come from a calibrated actor")
    profile = Profile.load(args.profile)
    lab = labeller_for(profile)
    out, columns = label_take(take, profile, labeller=lab)
    found = float((columns >= 0).mean()) if columns.size else 0.0
    print(f"{args.take}: {take.n_frames} frames, {take.n_markers} point slots -> {len(profile.labels)} labels, "
          f"{100 * found:.1f} % of label-frames found, {lab.initialisations} track start(s)")
    return out


def run(args: argparse.Namespace) -> int:
    from transport.takefile import read_take, write_take

    take = read_take(args.take)
    out = labelled_take(args, take)
    write_take(out, args.out)
    print(f"wrote {args.out}")
    return 0
