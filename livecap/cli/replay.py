"""``livecap replay``: solve a take and render the preview (MP4 and/or PNG frames) offscreen.

With ground truth beside the take (``<take>.truth.npz``), each frame is side by side: ground
truth on the left, the solve on the right (white ticks on its weight bars mark the truth).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from livecap.calibration.stabilise import to_quaternion
from livecap.cli.common import (
    add_take_solve_arguments,
    load_rig,
    profile_for,
    progress_bar,
    solver_options,
)
from livecap.cli.progress import stage
from livecap.cli.retarget_args import add_retarget_arguments
from livecap.demo import truth_path
from livecap.modes.registry import build_solver
from livecap.offline.solve import prepare_targets
from transport.takefile import is_weights_take, read_take


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 640x480, got {text!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise argparse.ArgumentTypeError(f"size {w}x{h} out of range")
    return w, h


def register(sub) -> None:
    p = sub.add_parser("replay", help="solve a take and render a preview video / PNG frames (offscreen)",
                       description="Solve a recorded take and render the rig offscreen (EGL) to MP4 and/or PNG.")
    add_take_solve_arguments(p)
    p.add_argument("--preview", help="MP4 video to write")
    p.add_argument("--frames", help="folder for PNG frames (frame_<number>.png)")
    p.add_argument("--size", type=_size, default=(640, 480), help="panel size WxH (default 640x480)")
    p.add_argument("--every", type=int, default=1, help="render every Nth frame (default 1)")
    p.add_argument("--msaa", type=int, default=4, help="multisample anti-aliasing samples (0: off; default 4)")
    p.add_argument("--truth", help="ground truth .npz (default: <take>.truth.npz when present)")
    p.add_argument("--no-truth", action="store_true", help="draw the solve alone even when ground truth exists")
    add_retarget_arguments(p)
    p.set_defaults(func=run)


def _solve(solver, targets: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weights for every frame and the solve latency per frame (s); offline solvers get their average."""
    T = len(targets)
    if hasattr(solver, "solve"):
        start = time.perf_counter()
        W = solver.solve(targets, valid)
        return W, np.full(T, (time.perf_counter() - start) / max(T, 1))
    W, lat = None, np.zeros(T)
    for i in range(T):
        start = time.perf_counter()
        w = solver.step(targets[i], valid[i])
        lat[i] = time.perf_counter() - start
        W = np.zeros((T, len(w))) if W is None else W
        W[i] = w
    return (np.zeros((0, 0)) if W is None else W), lat


def _load_truth(args, take_path: Path, rig, profile):
    from livecap.demo.performance import GroundTruth

    if args.no_truth:
        return None
    path = Path(args.truth) if args.truth else truth_path(take_path)
    if not path.exists():
        if args.truth:
            raise FileNotFoundError(f"{path}: no such ground truth file")
        return None
    try:
        truth = GroundTruth.load(path)
    except (OSError, KeyError, ValueError) as exc:
        raise ValueError(f"{path}: not a ground truth file ({exc})") from None
    missing = [n for n in rig.names if n not in truth.names]
    lost = [lab for lab in profile.labels if lab not in truth.labels]
    if missing or lost:
        raise ValueError(f"{path}: ground truth lacks shapes {missing[:4]} / markers {lost[:4]} of this rig")
    truth.weights = truth.weights[:, [truth.names.index(n) for n in rig.names]]
    truth.actor_neutral = np.asarray(truth.actor_neutral)[[truth.labels.index(lab) for lab in profile.labels]]
    return truth


def run(args: argparse.Namespace) -> int:
    if not args.preview and not args.frames:
        raise ValueError("nothing to write: give --preview out.mp4 and/or --frames DIR")
    if args.every < 1:
        raise ValueError("--every must be >= 1")
    if is_weights_take(args.take):
        return _weights_take(args)
    rig, layout = load_rig(args)
    take = read_take(args.take)
    profile = profile_for(args, rig, layout, take)
    solver = build_solver(args.mode, profile, solver_options(args))
    sel, targets, R, t = prepare_targets(take, profile)
    with stage(f"solving {take.n_frames} frames ({args.mode})"):
        W, latency = _solve(solver, targets, sel.valid)
    quats = to_quaternion(R)
    stabilised = targets + profile.source_neutral
    truth = _load_truth(args, Path(args.take), rig, profile)
    if truth is not None and len(truth.weights) != take.n_frames:
        raise ValueError(f"ground truth has {len(truth.weights)} frames, take has {take.n_frames}")

    from viewer.compose import Caption, top_shapes
    from viewer.offscreen import FrameWriter
    from viewer.preview import Preview
    from viewer.scene import Similarity

    w, h = args.size
    preview = Preview(rig, layout, profile, (w, h), samples=args.msaa)
    truth_head = Similarity.fit(profile.target_sites, truth.actor_neutral) if truth is not None else None
    out_size = (2 * w if truth is not None else w, h)
    frames = range(0, take.n_frames, args.every)
    start = time.perf_counter()
    with FrameWriter(args.preview, args.frames, take.rate / args.every, out_size) as writer, \
            progress_bar(f"rendering {len(frames)} frames", len(frames)) as update:
        for done, i in enumerate(frames, 1):
            number, when = take.first_frame + i, i / take.rate
            cap = Caption(number, when, latency[i] * 1e3, f"solved ({args.mode})")
            ref = order = None
            if truth is not None:
                ref = truth.weights[i]
                order = top_shapes(W[i], preview.bars, ref)
                cap.extra = f"weight RMSE {np.sqrt(np.mean((W[i] - ref) ** 2)):.3f}"
            img = preview.draw(W[i], quats[i], t[i], stabilised[i], sel.valid[i], cap, reference=ref, order=order)
            if truth is not None:
                left = preview.draw(truth.weights[i], truth.head_rotation[i], truth.head_translation[i],
                                    caption=Caption(number, when, title="ground truth"), head=truth_head,
                                    order=order)
                img = np.hstack([left, img])
            writer.write(img, number)
            update(done, len(frames))
    elapsed = time.perf_counter() - start
    where = " and ".join(str(p) for p in (args.preview, args.frames) if p)
    print(f"{where}: {writer.count} frames {out_size[0]}x{out_size[1]} at {take.rate / args.every:g} fps "
          f"({writer.count / max(elapsed, 1e-9):.1f} frames/s rendered)"
          + (", ground truth on the left" if truth is not None else ""))
    return 0


def _weights_take(args: argparse.Namespace) -> int:
    """A Live Link Face CSV: the rig driven by its curves (by name, --map or --transfer) and its head angles."""
    from livecap.cli.retarget_args import describe, load_target, retargeter
    from livecap.retarget.take import retarget_curves
    from transport.llf_csv import read_llf_csv
    from viewer.compose import Caption
    from viewer.offscreen import FrameWriter
    from viewer.preview import Preview

    rig, layout = load_target(args)
    solved = retarget_curves(read_llf_csv(args.take), retargeter(args, rig, layout))
    preview = Preview(rig, None, None, args.size, samples=args.msaa)
    frames = range(0, len(solved.weights), args.every)
    title = f"Live Link Face, {describe(args)}"
    with FrameWriter(args.preview, args.frames, solved.rate / args.every, args.size) as writer, \
            progress_bar(f"rendering {len(frames)} frames", len(frames)) as update:
        for done, i in enumerate(frames, 1):
            number = solved.first_frame + i
            img = preview.draw(solved.weights[i], solved.head_rotation[i], np.zeros(3),
                               caption=Caption(number, i / solved.rate, title=title))
            writer.write(img, number)
            update(done, len(frames))
    where = " and ".join(str(p) for p in (args.preview, args.frames) if p)
    print(f"{where}: {writer.count} frames {args.size[0]}x{args.size[1]} at {solved.rate / args.every:g} fps")
    return 0
