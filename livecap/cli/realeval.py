"""``livecap realeval``: every mode on takes driven by real performances, against the oracle.

For each rig, noise level and Live Link Face CSV: a take of a new actor performing the CSV's
curves (livecap.demo.curves_take), plain calibration on its neutral take, each mode's solve, and
the per-frame bounded least-squares oracle with the true actor basis and pose
(livecap.offline.real_eval). Printed per take and summarised over the files as ratios to the oracle.

Each file's take has its own noise, occlusion and neutral draw (``curves_take.take_seed`` of the file's name, the base
``--seed`` and the draw index); ``--draws N`` solves N draws per file, so a difference smaller than the spread between
draws shows as such. Until 2026-12-06 every take was seeded with 1: five of the six files shared one draw.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

REALDATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata"
DEFAULT_MODES = ["auto", "robust", "robust-lag", "movement", "a2f"]  # a2f: the peer baseline (issue 41.7)


def _realdata() -> Path:
    import os

    env = os.environ.get("LIVECAP_SHARED")
    return Path(env) / "realdata" if env else REALDATA.resolve()


def register(sub) -> None:
    p = sub.add_parser("realeval", help="accuracy on takes driven by real performances, as ratios to the oracle",
                       description="Weight RMSE and vertex p95 as ratios to the true-basis, true-pose oracle, "
                                   "jitter x truth and blink peak retention, per take and over the files.")
    p.add_argument("--curves", nargs="+", help="Live Link Face CSVs (default: every CSV in "
                   "$LIVECAP_SHARED/realdata/performance or ../shared/realdata/performance)")
    p.add_argument("--rig", nargs="+", default=["ict", "demo"],
                   help="rigs: 'ict' (../shared/realdata/ict-face), 'demo' (bundled), or a rig path with its "
                        "markers.json (default: ict demo)")
    p.add_argument("--markers", help="markers.json for a rig given by path that has none beside it "
                   "(e.g. the one 'livecap rig transfer' wrote)")
    p.add_argument("--mapping", help="ARKit name mapping JSON for rigs whose names are not ARKit's")
    p.add_argument("--noise", type=float, nargs="+", default=[0.2, 0.5], help="marker noise sigma(s), mm")
    p.add_argument("--occlusion", type=float, default=0.05, help="fraction of marker-frames missing (bursts)")
    p.add_argument("--seconds", type=float, default=20.0, help="length of each take (default 20 s)")
    p.add_argument("--start", type=float, default=10.0, help="seconds into each CSV (clamped to fit; default 10)")
    p.add_argument("--modes", nargs="+", default=DEFAULT_MODES, help=f"modes (default {' '.join(DEFAULT_MODES)})")
    p.add_argument("--seed", type=int, default=1, help="base seed of the takes' draws; each file and draw gets its "
                   "own from it and the file's name (default 1)")
    p.add_argument("--draws", type=int, default=1, help="noise / occlusion / neutral draws per file; the summary is "
                   "the mean over files and draws, with the per-draw means' min-max (default 1)")
    p.add_argument("--json", help="write every row as JSON")
    p.add_argument("--no-prior", action="store_true", help="the profile carries no animation prior (so auto is "
                   "robust, kalman fits under a ridge); by default it carries one built from the other files "
                   "(leave one file out), as 'livecap calibrate --prior' stores it")
    p.add_argument("--warp", default="rbf", choices=["rbf", "similarity", "rigid"],
                   help="the calibration's proportion match, as 'livecap calibrate --warp' (default rbf)")
    p.add_argument("--bias", action="store_true", help="per take and mode, the shapes with the largest mean signed "
                   "error and how many of the truly active shapes (> 0.05) the solve keeps active")
    p.add_argument("--actor-rig", metavar="RIG", help="model mismatch: this other rig (e.g. the MakeHuman head, with "
                   "--actor-mapping) acts, its markers bound to each --rig ('livecap generate --actor-rig'); no oracle")
    p.add_argument("--actor-mapping", help="ARKit name mapping JSON for --actor-rig")
    p.set_defaults(func=run)


def _rig(name: str, markers: str | None = None):
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.demo import DEMO_MARKERS, DEMO_RIG
    from transport.rig_files import load_rig

    if name == "demo":
        rec = Path(__file__).resolve().parents[2] / "recordings"
        rig = Rig.load(rec / DEMO_RIG)
        return rig, MarkerLayout.load(rec / DEMO_MARKERS, rig)
    path = _realdata() / "ict-face" if name == "ict" else Path(name)
    if not path.exists():
        raise ValueError(f"{path}: rig not found")
    rig = load_rig(path)
    mpath = path / "markers.json" if path.is_dir() else path.with_name(path.stem + ".markers.json")
    mpath = Path(markers) if markers and not mpath.exists() else mpath
    if not mpath.exists():
        raise ValueError(f"{mpath}: no markers.json for rig {path}")
    return rig, MarkerLayout.load(mpath, rig)


def run(args: argparse.Namespace) -> int:
    from livecap.demo.curves_take import CurveTakeSettings, curves_take, take_seed
    from livecap.offline.real_eval import Row, evaluate_curve_take
    from transport.arkit import load_mapping
    from transport.llf_csv import read_llf_csv

    files = [Path(c) for c in args.curves] if args.curves else sorted((_realdata() / "performance").glob("*.csv"))
    if not files:
        raise ValueError(f"{_realdata() / 'performance'}: no Live Link Face CSVs (give --curves)")
    if args.draws < 1:
        raise ValueError(f"--draws {args.draws}: at least 1")
    mapping = load_mapping(args.mapping) if args.mapping else None
    out = []
    for rig_name in args.rig:
        rig, layout = _rig(rig_name, args.markers)
        anatomy = {}  # the actor's marker sites, once per rig (livecap.demo.mismatch_take.actor_layout)
        for noise in args.noise:
            for f, draw in [(f, d) for f in files for d in range(args.draws)]:
                length = read_llf_csv(f).times[-1]
                start = max(0.0, min(args.start, length - args.seconds))
                seed = take_seed(f, args.seed, draw)
                s = CurveTakeSettings(start=start, seconds=args.seconds, noise_mm=noise, occlusion=args.occlusion,
                                      seed=seed)
                t0 = time.perf_counter()
                ct = curves_take(rig, layout, f, s, mapping) if not args.actor_rig else \
                    _mismatch(args, rig, layout, f, start, noise, anatomy, seed)
                options = {"kalman": {"rate": ct.take.rate}}  # the IMM's process noise is per second
                others = [o for o in files if o != f]
                prior = None
                if not args.no_prior and others:
                    from livecap.calibration.animation_prior import build_prior

                    prior = build_prior(others, rig.names, rig.lower, rig.upper, mapping)
                rows = evaluate_curve_take(rig, getattr(ct, "layout", layout), ct, args.modes, options, prior,
                                           args.warp)
                oracle = rows[0] if rows[0].mode == "oracle" else Row("none", *[float("nan")] * 5)
                took = time.perf_counter() - t0
                print(f"{rig_name} {noise:g} mm {f.name} draw {draw} seed {seed} ({ct.take.n_frames} frames, "
                      f"{took:.0f} s): "
                      + (f"oracle RMSE {oracle.rmse:.3f} p95 {oracle.p95_mm:.2f} mm" if oracle.mode == "oracle"
                         else f"actor {args.actor_rig}, no oracle"))
                for r in rows:
                    rec = {"rig": rig_name, "noise_mm": noise, "file": f.name, "draw": draw, "base_seed": args.seed,
                           "seed": seed, **vars(r),
                           "rmse_x": r.rmse / oracle.rmse, "p95_x": r.p95_mm / oracle.p95_mm}
                    if not args.bias:
                        rec.pop("bias")
                    out.append(rec)
                    print(f"  {r.mode:12s} RMSE {r.rmse:.3f} ({rec['rmse_x']:.2f}x)  p95 {r.p95_mm:.2f} mm "
                          f"({rec['p95_x']:.2f}x)  jitter {r.jitter_x:7.2f}x  blink {r.blink:.2f}  "
                          f"phantom {r.phantom:.3f}" + (f"  RMSE vs curves {r.rmse_curves:.3f}"
                                                        if np.isfinite(r.rmse_curves) else ""))
                    if args.bias:
                        worst = sorted(r.bias.items(), key=lambda kv: -abs(kv[1]))[:5]
                        print(f"    active kept {r.active_kept:.1f} of {r.active_true:.1f}; bias "
                              + "  ".join(f"{n} {b:+.3f}" for n, b in worst))
    print(summary_table(out, args.bias))
    for line in ahead_of(out):
        print(line)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"machine": platform.node(), "date": time.strftime("%Y-%m-%d"),
                                               "seconds": args.seconds, "occlusion": args.occlusion,
                                               "seed": args.seed, "draws": args.draws,
                                               "rows": out}, indent=1))
    return 0


def _mismatch(args: argparse.Namespace, rig, layout, f: Path, start: float, noise: float, anatomy: dict,
              seed: int):
    """The model-mismatch take of ``f``; ``anatomy`` caches the actor's marker sites (the slow rig transfer)."""
    from livecap.demo.mismatch_take import MismatchSettings, actor_layout, mismatch_take
    from transport.arkit import load_mapping
    from transport.rig_files import load_rig

    actor = anatomy.get("actor") or load_rig(args.actor_rig)
    if "sites" not in anatomy:
        anatomy.update(actor=actor, sites=actor_layout(actor, rig, layout))
    mapping = load_mapping(args.actor_mapping) if args.actor_mapping else None
    return mismatch_take(actor, rig, layout, f, mapping, MismatchSettings(start=start, seconds=args.seconds,
                                                                          noise_mm=noise, occlusion=args.occlusion,
                                                                          seed=seed),
                         anatomy["sites"])


def summary_table(rows: list[dict], kept: bool = False) -> str:
    """Markdown: per rig, noise and mode, the mean over files and draws (oracle's absolute figures beside); with more
    than one draw, the min-max over draws of the per-draw means of RMSE x, p95 x and jitter (a difference inside it
    is the draw's, not the method's); ``kept``: the truly active shapes the solve keeps active, and the solve's mean
    absolute per-shape bias."""
    draws = len({r.get("draw", 0) for r in rows}) > 1
    lines = ["| rig | noise mm | mode | weight RMSE (x oracle) | vertex p95 mm (x oracle) | jitter x truth "
             "| blink kept |" + (" per draw min-max: RMSE x / p95 x / jitter |" if draws else "")
             + (" active kept / true | mean abs bias |" if kept else ""),
             "|---|---|---|---|---|---|---|" + ("---|" if draws else "") + ("---|---|" if kept else "")]
    keys = []
    for r in rows:
        k = (r["rig"], r["noise_mm"], r["mode"])
        if k not in keys:
            keys.append(k)
    for k in keys:
        sel = [r for r in rows if (r["rig"], r["noise_mm"], r["mode"]) == k]

        def mean(field: str, sel=sel) -> float:
            return _finite_mean([r[field] for r in sel])

        extra = ""
        if draws:
            extra += " " + " / ".join("{:.2f}-{:.2f}".format(*spread(sel, field))
                                      for field in ("rmse_x", "p95_x", "jitter_x")) + " |"
        if kept:
            bias = np.mean([np.mean(np.abs(list(r["bias"].values()))) for r in sel])
            extra += f" {mean('active_kept'):.1f} / {mean('active_true'):.1f} | {bias:.3f} |"
        lines.append(f"| {k[0]} | {k[1]:g} | {k[2]} | {mean('rmse'):.3f} ({mean('rmse_x'):.2f}) | "
                     f"{mean('p95_mm'):.2f} ({mean('p95_x'):.2f}) | {mean('jitter_x'):.2f} | {mean('blink'):.2f} |"
                     + extra)
    return "\n".join(lines)


def spread(rows: list[dict], field: str) -> tuple[float, float]:
    """(min, max) over draws of ``field``'s mean over the files of that draw (non-finite values left out)."""
    means = [_finite_mean([r[field] for r in rows if r.get("draw", 0) == d]) for d in {r.get("draw", 0) for r in rows}]
    means = [m for m in means if np.isfinite(m)]
    return (min(means), max(means)) if means else (float("nan"), float("nan"))


def _finite_mean(values: list) -> float:
    """The mean of the finite values (a take without an oracle has NaN ratios), NaN when there are none."""
    vals = np.array(values, dtype=float)
    return float(np.mean(vals[np.isfinite(vals)])) if np.isfinite(vals).any() else float("nan")


def ahead_of(rows: list[dict], mode: str = "auto", peer: str = "a2f") -> list[str]:
    """Per rig and noise, in how many (file, draw, path) ``mode`` beats ``peer`` on weight RMSE, vertex p95 *and*
    jitter (issue 41: the default ahead of the Audio2Face-3D baseline on every held-out file), and where it does not."""
    pairs: dict[tuple, dict[str, dict]] = {}
    for r in rows:
        label, path = r["mode"].rsplit(" ", 1) if " " in r["mode"] else (r["mode"], "offline")
        key = (r["rig"], r["noise_mm"], r["file"], r.get("draw", 0), path)
        pairs.setdefault(key, {})[label.split("=")[0]] = r
    lines = []
    for rig, noise in dict.fromkeys(k[:2] for k in pairs):
        both = {k: v for k, v in pairs.items() if k[:2] == (rig, noise) and mode in v and peer in v}
        if not both:
            continue
        lost = {k: [f for f in ("rmse", "p95_mm", "jitter_x") if not v[mode][f] < v[peer][f]] for k, v in both.items()}
        lines.append(f"{rig} {noise:g} mm: {mode} ahead of {peer} on RMSE, p95 and jitter in "
                     f"{sum(not v for v in lost.values())} of {len(both)} (file, draw, path)"
                     + "".join(f"; not {k[2]} draw {k[3]} {k[4]} ({', '.join(v)})" for k, v in lost.items() if v))
    return lines
