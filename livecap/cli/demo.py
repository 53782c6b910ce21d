"""``livecap demo``: replay the bundled take through a solver and report accuracy against ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from livecap.cli.common import load_rig, profile_for, progress_bar
from livecap.demo import DEMO_RIG, DEMO_TAKE, truth_path
from livecap.demo.performance import GroundTruth
from livecap.modes.registry import DEFAULT_MODE, MODE_HELP, MODES_AND_AUTO, build_solver, resolve_mode
from livecap.offline.metrics import jitter, vertex_error, weight_rmse
from livecap.offline.solve import solve_take
from transport.takefile import read_take
from transport.weights_csv import write_weights_csv

RECORDINGS = Path(__file__).resolve().parents[2] / "recordings"


def register(sub) -> None:
    p = sub.add_parser("demo", help="solve the bundled demo take and print accuracy against ground truth")
    p.add_argument("--recordings", default=str(RECORDINGS), help="folder with the demo files")
    p.add_argument("--mode", default=DEFAULT_MODE, choices=sorted(MODES_AND_AUTO), help=MODE_HELP)
    p.add_argument("--out", default="out/demo_weights.csv", help="weights CSV to write")
    p.set_defaults(func=run, neutral_seconds=1.0, profile=None, markers=None)


def run(args: argparse.Namespace) -> int:
    rec = Path(args.recordings)
    args.rig = str(rec / DEMO_RIG)
    rig, layout = load_rig(args)
    take = read_take(rec / DEMO_TAKE)
    truth = GroundTruth.load(truth_path(rec / DEMO_TAKE))
    profile = profile_for(args, rig, layout, take)
    mode = resolve_mode(args.mode, profile)
    solver = build_solver(mode, profile)
    with progress_bar(f"solving {DEMO_TAKE} ({mode})", take.n_frames) as update:
        solved = solve_take(take, profile, solver, progress=update)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_weights_csv(args.out, solved.names, solved.weights, solved.rate, solved.first_frame)
    W = solved.weights
    mean_mm, max_mm = vertex_error(rig, W, truth.weights)
    print(f"take      {DEMO_TAKE}: {take.n_frames} frames at {take.rate:g} Hz, {take.n_markers} markers, "
          f"{(~take.valid).mean() * 100:.1f}% missing")
    print(f"rig       {rig.n_shapes} shapes, {rig.n_vertices} vertices")
    print(f"mode      {mode}: {solved.solve_seconds * 1e3 / take.n_frames:.3f} ms/frame")
    print(f"weight RMSE       {weight_rmse(W, truth.weights):.4f}")
    print(f"vertex error (mm) mean {mean_mm:.3f}  max {max_mm:.3f}")
    print(f"jitter ratio      {jitter(W) / max(jitter(truth.weights), 1e-12):.2f} (solved / ground truth)")
    print(f"weights written   {args.out}")
    return 0
