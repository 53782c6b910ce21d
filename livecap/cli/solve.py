"""``livecap solve``: a take file and a rig in, weight curves (CSV) out."""

from __future__ import annotations

import argparse
from pathlib import Path

from livecap.cli.common import (
    add_take_solve_arguments,
    load_rig,
    profile_for,
    progress_bar,
    saved_profile,
    solver_options,
)
from livecap.cli.movement_args import add_movement_arguments, movement_options
from livecap.cli.retarget_args import add_retarget_arguments
from livecap.modes.per_frame import QPSettings, check_keys
from livecap.modes.registry import build_solver, resolve_mode
from livecap.offline.glb import write_solved_glb
from livecap.offline.solve import solve_take
from transport.takefile import is_weights_take, read_take
from transport.weights_csv import write_weights_csv


def register(sub) -> None:
    p = sub.add_parser("solve", help="solve a take (C3D/TRC/CSV) for rig weights, write a weights CSV",
                       description="Solve every frame of a recorded take for the rig's blendshape weights.")
    add_take_solve_arguments(p)
    p.add_argument("--temporal", type=float, help=f"qp: weight gamma of |w - w_prev|^2 (default {QPSettings.temporal})")
    p.add_argument("--keys", help="keys JSON (what 'livecap rom' writes beside its range-of-motion take, or explicit "
                   "key pairs; docs/modes.md): required by --mode rbf and --basis actor")
    p.add_argument("--basis", choices=["rig", "actor"], default="rig",
                   help="qp: calibrated rig basis, or the actor's own from --keys (Curio 2006)")
    p.add_argument("--out", required=True, help="weights CSV: frame,time,<shape>...; or a .glb (glTF 2.0: mesh, "
                   "morph targets, weight and head-pose animation)")
    p.add_argument("--unlabelled", action="store_true",
                   help="the take's points are unlabelled or wrongly named: label them against --profile first")
    add_movement_arguments(p)
    add_retarget_arguments(p)
    p.set_defaults(func=run)


def solve_options(args: argparse.Namespace) -> dict:
    """The solver options ``livecap solve``'s flags give (a batch job's SolveSettings.options() equals it)."""
    return {**solver_options(args), "temporal": args.temporal, "keys": args.keys, "basis": args.basis,
            **movement_options(args)}


def run(args: argparse.Namespace) -> int:
    check_keys(args.mode, {"keys": args.keys, "basis": args.basis})
    glb = Path(args.out).suffix.lower() == ".glb"
    if is_weights_take(args.take):
        return _weights_take(args, glb)
    if args.profile and not (glb or args.unlabelled):
        rig = None
        take = read_take(args.take)
        profile = saved_profile(args, take)
    else:
        rig, layout = load_rig(args)
        take = read_take(args.take)
        if args.unlabelled:
            from livecap.cli.label import labelled_take

            take = labelled_take(args, take)
        profile = profile_for(args, rig, layout, take)
    options = solve_options(args)
    mode = resolve_mode(args.mode, profile, options)
    solver = build_solver(mode, profile, options)
    with progress_bar(f"solving ({mode})", take.n_frames) as update:
        solved = solve_take(take, profile, solver, progress=update)
    if glb:
        write_solved_glb(args.out, rig, solved, max(1, int(args.neutral_seconds * solved.rate)))
    else:
        write_weights_csv(args.out, solved.names, solved.weights, solved.rate, solved.first_frame)
    print(f"{args.out}: {take.n_frames} frames x {len(solved.names)} shapes "
          f"({solved.solve_seconds * 1e3 / take.n_frames:.3f} ms/frame)")
    return 0



def _weights_take(args: argparse.Namespace, glb: bool) -> int:
    """A Live Link Face CSV: its ARKit curves onto the rig (by name, --map or --transfer), no marker solve."""
    from livecap.cli.retarget_args import describe, load_target, retargeter
    from livecap.core.timecode import format_timecode
    from livecap.retarget.take import retarget_curves
    from transport.llf_csv import read_llf_csv

    curves = read_llf_csv(args.take)
    rig, layout = load_target(args)
    solved = retarget_curves(curves, retargeter(args, rig, layout))
    if glb:
        write_solved_glb(args.out, rig, solved, max(1, int(args.neutral_seconds * solved.rate)))
    else:
        write_weights_csv(args.out, solved.names, solved.weights, solved.rate, solved.first_frame)
    bad = f", {curves.bad} unreadable (first {curves.first_bad})" if curves.bad else ""
    print(f"{args.out}: {len(solved.weights)} frames x {len(solved.names)} shapes from a Live Link Face CSV "
          f"({len(curves.times)} rows from timecode {format_timecode(curves.start)}, "
          f"{curves.lost} tracking lost{bad}; {describe(args)})")
    return 0
