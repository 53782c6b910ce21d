"""``livecap evaluate``: every solver mode on one take with ground truth, side by side.

Modes come from livecap.modes.registry.MODES, so a newly registered mode shows up without touching this
file. Each mode gets the same calibrated profile and the same options (``keys`` from a labelled
ROM take, so example-based and actor-basis modes can run); a mode that cannot be built says why.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from livecap.cli.common import add_calibration_arguments, load_rig, profile_for, progress_bar
from livecap.demo import DEMO_RIG, DEMO_TAKE, truth_path
from livecap.demo.performance import GroundTruth, PerformanceSettings
from livecap.modes.registry import MODES, build_solver
from livecap.offline.metrics import (
    jitter,
    peak_retention,
    shape_bias,
    shape_indices,
    vertex_error_stats,
    weight_rmse,
)
from livecap.offline.real_eval import ACTIVE
from livecap.offline.solve import prepare_targets
from livecap.offline.streamed import stream_take
from transport.takefile import read_take

RECORDINGS = Path(__file__).resolve().parents[2] / "recordings"
# Extra rows beyond each mode's defaults: (label, mode, options).
VARIANTS = [("qp actor-basis", "qp", {"basis": "actor"}),
            ("qp ridge1 temp20", "qp", {"ridge": 1.0, "temporal": 20.0})]


def register(sub) -> None:
    p = sub.add_parser("evaluate", help="solve a take with ground truth in every mode; print accuracy and speed",
                       description="Weight RMSE, vertex error, jitter and time per frame for every solver mode.")
    p.add_argument("take", nargs="?", help=f"take with <take>.truth.npz beside it (default: bundled {DEMO_TAKE})")
    p.add_argument("--rig", help=f"rig (default: bundled {DEMO_RIG})")
    p.add_argument("--markers", help="markers.json (default: beside the rig)")
    add_calibration_arguments(p)
    p.add_argument("--truth", help="ground truth .npz (default: <take>.truth.npz)")
    p.add_argument("--keys", help="keys file (labelled ROM take) for modes that use keys; default for the "
                   "bundled demo: a ROM take of the same actor, generated on the fly")
    p.add_argument("--modes", nargs="+", help="only these modes (default: all registered)")
    p.add_argument("--frames", type=int, default=0, help="evaluate only the first N frames (default all)")
    p.add_argument("--ridge", type=float, default=None, help="ridge passed to every mode (default: the mode's)")
    p.add_argument("--json", help="also write the table as JSON")
    p.set_defaults(func=run)


def _demo_keys(rig, layout) -> Path:
    from livecap.demo.rom import DEMO_ROM_KEYS, generate_rom

    tag = hashlib.sha1(rig.deltas.tobytes()[:1 << 20] + "|".join(layout.labels).encode()).hexdigest()[:10]
    out = Path(tempfile.gettempdir()) / f"livecap-demo-rom-{tag}"
    if not (out / DEMO_ROM_KEYS).exists():
        generate_rom(out, rig, layout, PerformanceSettings(seed=50))
    return out / DEMO_ROM_KEYS


def evaluate_mode(solver, targets: np.ndarray, valid: np.ndarray, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """Weights (T x m) and per-frame solve times in seconds (one total for offline ``solve``)."""
    if hasattr(solver, "solve"):
        t0 = time.perf_counter()
        W = solver.solve(targets, valid)
        return np.asarray(W), np.array([(time.perf_counter() - t0) / max(len(targets), 1)])
    times = np.empty(len(targets))
    W = None
    for i in range(len(targets)):
        t0 = time.perf_counter()
        w = solver.step(targets[i], valid[i])
        times[i] = time.perf_counter() - t0
        if W is None:
            W = np.zeros((len(targets), len(w)))
        W[i] = w
        if progress is not None:
            progress(i + 1, len(targets))
    return W, times


def _ratio(x: float) -> str:
    return f"{'-':>5s}" if np.isnan(x) else f"{x:5.2f}"


def _print_bias(table: list[dict], top: int = 3) -> None:
    """Per mode, the shapes with the largest mean signed error (positive: over-driven)."""
    print("largest per-shape bias (mean solved - true weight):")
    for row in table:
        if "bias" in row:
            worst = sorted(row["bias"].items(), key=lambda kv: -abs(kv[1]))[:top]
            print(f"  {row['mode']:24s} " + "  ".join(f"{n} {b:+.3f}" for n, b in worst)
                  + f"  (active kept {row['active_kept']:.1f} of {row['active_true']:.1f})")


def run(args: argparse.Namespace) -> int:
    demo = args.take is None
    take_path = Path(args.take) if args.take else RECORDINGS / DEMO_TAKE
    args.rig = args.rig or str(RECORDINGS / DEMO_RIG)
    rig, layout = load_rig(args)
    take = read_take(take_path)
    tpath = Path(args.truth) if args.truth else truth_path(take_path)
    if not tpath.exists():
        raise ValueError(f"{tpath}: no ground truth for {take_path} (give --truth)")
    truth = GroundTruth.load(tpath)
    if truth.names != list(rig.names):
        raise ValueError(f"{tpath}: ground truth shapes differ from the rig's")
    if args.frames:
        take = take.slice(0, args.frames)
    W_true = truth.weights[: take.n_frames]
    profile = profile_for(args, rig, layout, take)
    sel, targets, _, _ = prepare_targets(take, profile)
    valid = sel.valid  # the gap-filled mask, exactly what `livecap solve` hands the solver
    options: dict = {}
    keys_path = args.keys or (_demo_keys(rig, layout) if demo else None)
    if keys_path:
        from livecap.calibration.keys import load_keys

        options["keys"] = load_keys(keys_path, profile)
    if args.ridge is not None:
        options["ridge"] = args.ridge
    rows = [(name, name, {}) for name in sorted(MODES)] + VARIANTS
    if args.modes:
        rows = [r for r in rows if r[1] in args.modes or r[0] in args.modes]
    truth_jitter = max(jitter(W_true), 1e-12)
    print(f"take {take_path.name}: {take.n_frames} frames at {take.rate:g} Hz, {take.n_markers} markers, "
          f"{(~take.valid).mean() * 100:.1f}% missing; rig {rig.n_shapes} shapes, {rig.n_vertices} vertices"
          + (f"; keys {Path(keys_path).name} ({len(options['keys'].names)} keys)" if keys_path else ""))
    header = f"{'mode':24s} {'weight RMSE':>11s} {'vertex mm':>9s} {'p95 mm':>7s} {'max mm':>7s} {'jitter x':>8s} " \
             f"{'blink':>5s} {'jaw':>5s} {'ms/frame':>8s} {'p99 ms':>7s}"
    print(header)
    table = []
    blinks, jaws = shape_indices(rig.names, "blink"), shape_indices(rig.names, "jawopen")
    quiet = logging.getLogger("livecap.modes")
    for label, mode, extra in rows:
        level, quiet.level = quiet.level, logging.WARNING  # mode build notes would break the table
        try:
            solver = build_solver(mode, profile, {**options, **extra})
        except (ValueError, OSError, KeyError) as exc:
            print(f"{label:24s} unavailable: {exc}")
            table.append({"mode": label, "error": str(exc)})
            continue
        finally:
            quiet.setLevel(level)
        with progress_bar(f"{label}", take.n_frames) as update:
            W, times = evaluate_mode(solver, targets, valid, update)
        runs = [(label, "offline", W, times)]
        if hasattr(solver, "step"):  # as `livecap run` feeds it: causal head pose, no gap filling
            st = stream_take(take, profile, mode, {**options, **extra})
            runs.append((f"{label} stream", "stream", st.weights,
                         np.array([st.step_ms["p50_ms"], st.step_ms["p99_ms"]]) / 1e3))
        for row_label, kind, W, times in runs:
            vert = vertex_error_stats(rig, W, W_true)
            bias = shape_bias(W, W_true)
            row = {"mode": row_label, "kind": kind, "weight_rmse": weight_rmse(W, W_true), "vertex_mm": vert["mean"],
                   "vertex_p95_mm": vert["p95"], "vertex_max_mm": vert["max"],
                   "jitter_ratio": jitter(W) / truth_jitter,
                   "blink_peak": peak_retention(W, W_true, blinks), "jaw_peak": peak_retention(W, W_true, jaws),
                   "bias": dict(zip(rig.names, bias.tolist(), strict=True)),
                   "active_true": float((W_true > ACTIVE).sum(1).mean()),
                   "active_kept": float(((W_true > ACTIVE) & (W > ACTIVE)).sum(1).mean()),
                   "ms_per_frame": float(np.mean(times)) * 1e3 if kind == "offline" else float(times[0]) * 1e3,
                   "p99_ms": float(np.percentile(times, 99)) * 1e3 if kind == "offline" and len(times) > 1
                   else float(times[1]) * 1e3 if kind == "stream" else None}
            table.append(row)
            p99 = f"{row['p99_ms']:7.3f}" if row["p99_ms"] is not None else f"{'-':>7s}"
            print(f"{row_label:24s} {row['weight_rmse']:11.4f} {vert['mean']:9.3f} {vert['p95']:7.3f} "
                  f"{vert['max']:7.3f} {row['jitter_ratio']:8.2f} {_ratio(row['blink_peak'])} "
                  f"{_ratio(row['jaw_peak'])} {row['ms_per_frame']:8.3f} {p99}")
    _print_bias(table)
    print("(rows: what `livecap solve` gives (smoothed head pose, filled gaps); '<mode> stream': fed frame by frame "
          "through the live pipeline as `livecap run` feeds it, ms/frame = its step's p50)")
    print("(vertex p95: 95th percentile over frames of each frame's worst vertex; blink / jaw: solved peak over "
          "true peak, mean over true peaks >= half the largest; bias: mean solved - true weight; active kept: "
          "shapes > 0.05 in the truth that the solve has > 0.05 too, mean per frame)")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"take": str(take_path), "frames": take.n_frames, "rows": table},
                                              indent=1))
    return 0
