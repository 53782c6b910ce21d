"""``livecap noise-study``: every solver mode on a generated noisy take, against its ground truth.

Generates a take with ``livecap.demo.performance.perform`` (configurable noise and occlusion),
calibrates from its neutral span, selects the regularisation from the take
(``livecap.modes.robust.tune_profile``), then solves it with every mode in MODES, plus a 1€-filtered
variant of each mode that lacks one, and prints weight RMSE, vertex error (mm), jitter ratio
(solved / ground-truth mean |second difference|), added latency (frames, the cross-correlation
lag of solved against true curves) and blink peak amplitude. Also a sweep of the ridge against
the selected value, and a PNG of a few weight curves against the truth.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livecap.calibration.profile import calibrate, estimate_neutral
from livecap.cli.common import add_rig_arguments, load_rig, progress_bar
from livecap.demo.performance import PerformanceSettings, perform
from livecap.modes.registry import MODES
from livecap.modes.robust import (
    ROBUST_MODES,
    filtered,
    imm_filter,
    marker_filter,
    robust_settings,
    robust_solver,
    sparse_fit,
    tune_profile,
)
from livecap.offline.metrics import jitter, peak_retention, shape_indices, vertex_error, weight_rmse
from livecap.offline.solve import prepare_targets
from solvers.filters import FilteredSolver, OneEuroFilter
from solvers.sparse_fit import SPARSE_GRID


def register(sub) -> None:
    p = sub.add_parser("noise-study", help="every solver mode on a generated noisy take: accuracy, jitter, lag",
                       description=__doc__.split("\n\n")[1])
    add_rig_arguments(p)
    p.add_argument("--noise-mm", type=float, default=0.5, help="marker noise sigma in mm (default 0.5)")
    p.add_argument("--occlusion", type=float, default=0.05, help="fraction of marker-frames missing (default 0.05)")
    p.add_argument("--seconds", type=float, default=20.0, help="length of the generated take (default 20)")
    p.add_argument("--rate", type=float, default=120.0, help="frame rate of the generated take in Hz (default 120)")
    p.add_argument("--seed", type=int, default=1, help="performance seed (curves, head motion, noise)")
    p.add_argument("--modes", nargs="*", help="only these modes (default: all registered, + filtered variants)")
    p.add_argument("--no-sweep", action="store_true", help="skip the ridge sweep and the jitter/lag/blink trade-off")
    p.add_argument("--plot", default="out/noise_study.png", help="PNG of weight curves ('' for none)")
    p.add_argument("--json", help="also write the table as JSON")
    p.set_defaults(func=run)


# ----------------------------------------------------------------------------- measures
def lag_frames(solved: np.ndarray, truth: np.ndarray, max_lag: int = 30) -> float:
    """Delay (frames) maximising the cross-correlation of the mean-removed curves, summed over shapes.

    Positive: the solve trails the truth. Sub-frame by a parabola through the peak.
    """
    a = solved - solved.mean(0)
    b = truth - truth.mean(0)
    T = len(a)
    max_lag = min(max_lag, T - 2)
    lags = np.arange(-max_lag, max_lag + 1)
    # mean (not sum) over the overlap, so the shorter overlaps at large |lag| do not skew the peak
    c = np.array([np.mean(a[k:] * b[:T - k]) if k >= 0 else np.mean(a[:T + k] * b[-k:]) for k in lags])
    i = int(np.argmax(c))
    off = 0.0
    if 0 < i < len(c) - 1:
        y0, y1, y2 = c[i - 1:i + 2]
        den = y0 - 2 * y1 + y2
        off = 0.5 * (y0 - y2) / den if den != 0 else 0.0
    return float(lags[i] + off)


def percent(ratio: float) -> str:
    """A peak ratio as a percentage; "n/a" when the take has no true peak to compare with."""
    return "n/a" if np.isnan(ratio) else f"{ratio * 100:.0f}%"


def blink_indices(names: list[str]) -> list[int]:
    return shape_indices(names, "blink")


def blink_amplitude(solved: np.ndarray, truth: np.ndarray, names: list[str], window: int = 6) -> float:
    """Mean ratio of the solved peak (within +-window frames) to the true eyeBlink peak (peaks >= 0.5)."""
    return peak_retention(solved, truth, blink_indices(names), 0.5, window)


@dataclass
class Row:
    mode: str
    kind: str  # streaming / offline / lookahead
    rmse: float
    vertex_mm: float
    jitter_ratio: float
    lag: float
    blink: float
    ms_per_frame: float

    def line(self) -> str:
        return (f"{self.mode:22s} {self.kind:10s} {self.rmse:8.4f} {self.vertex_mm:8.3f} {self.jitter_ratio:9.2f} "
                f"{self.lag:7.2f} {percent(self.blink):>6s} {self.ms_per_frame:7.3f}")


HEADER = (f"{'mode':22s} {'kind':10s} {'RMSE':>8s} {'vert mm':>8s} {'jitter x':>9s} {'lag fr':>7s} "
          f"{'blink':>6s} {'ms/fr':>7s}")


def run_solver(solver, targets: np.ndarray, valid: np.ndarray, stream: bool, update=None) -> tuple[np.ndarray, float]:
    import time

    start = time.perf_counter()
    if not stream and hasattr(solver, "solve"):
        W = solver.solve(targets, valid)
    else:
        if hasattr(solver, "reset"):
            solver.reset()
        W = np.array([solver.step(targets[t], valid[t]) for t in range(len(targets))])
    ms = (time.perf_counter() - start) * 1e3 / len(targets)
    return W, ms


def variants(selected: list[str] | None) -> list[tuple[str, object]]:
    """(name, factory) for every registered mode and a 1€-filtered twin of each non-robust one."""
    out = []
    for name in sorted(MODES):
        out.append((name, MODES[name]))
        if name not in ROBUST_MODES:
            out.append((f"{name}+1e", filtered(MODES[name])))
    if selected:
        out = [(n, f) for n, f in out if n in selected]
        if not out:
            raise ValueError(f"no such modes {selected} (registered: {sorted(MODES)})")
    return out


def run(args: argparse.Namespace) -> int:
    rig, layout = load_rig(args)
    s = PerformanceSettings(seconds=args.seconds, rate=args.rate, noise_mm=args.noise_mm, occlusion=args.occlusion,
                            seed=args.seed)
    perf = perform(rig, layout, s)
    take, truth = perf.take, perf.weights
    neutral = estimate_neutral(take, layout.stable, max(1, int(s.neutral_start * take.rate)))
    profile = calibrate(rig, layout, neutral)
    _, targets, _, _ = prepare_targets(take, profile)
    tuned = tune_profile(profile, targets, take.valid, take.rate)
    tj = max(jitter(truth), 1e-12)
    print(f"take: {take.n_frames} frames at {take.rate:g} Hz, {take.n_markers} markers, {rig.n_shapes} shapes, "
          f"noise {args.noise_mm:g} mm, {(~take.valid).mean() * 100:.1f}% missing (seed {args.seed})")
    print(f"selected: noise {tuned['noise_mm']:.3f} mm (estimated); sparse-fit ridge {tuned['sparse_ridge']:.3g} "
          f"({tuned['sparse_criterion']}); plain prior-fit ridge {tuned['ridge']:.3g} ({tuned['criterion']}), "
          f"GCV {tuned['ridge_gcv']:.3g}")

    rows: list[Row] = []
    curves: dict[str, np.ndarray] = {}
    todo = []
    for name, factory in variants(args.modes):
        try:
            solver = factory(profile, {"rate": take.rate})
        except ValueError as e:  # a mode needing more than a rig and a neutral (e.g. rbf's key pairs)
            print(f"skipped {name}: {e}")
            continue
        offline = hasattr(solver, "solve")
        todo.append((name, solver, "offline" if offline else "streaming", False))
        if offline and hasattr(solver, "latency_frames"):
            todo.append((f"{name}@stream", factory(profile, {"rate": take.rate}), "lookahead", True))
    with progress_bar("noise study", len(todo)) as update:
        for i, (name, solver, kind, stream) in enumerate(todo):
            W, ms = run_solver(solver, targets, take.valid, stream)
            mean_mm, _ = vertex_error(rig, W, truth)
            rows.append(Row(name, kind, weight_rmse(W, truth), mean_mm, jitter(W) / tj, lag_frames(W, truth),
                            blink_amplitude(W, truth, rig.names), ms))
            curves[name] = W
            update(i + 1, len(todo))
    print(HEADER)
    for r in rows:
        print(r.line())
    summary = summarise(rows)
    for line in summary["lines"]:
        print(line)

    sweep = trade = None
    if not args.no_sweep:
        sweep = ridge_sweep(profile, targets, take.valid, truth, tuned["sparse_ridge"], take.rate)
        print(f"ridge sweep (robust mode): selected {tuned['sparse_ridge']:.3g} ({tuned['sparse_criterion']}) -> "
              f"RMSE {sweep['selected_rmse']:.4f}; sweep optimum {sweep['best_ridge']:.3g} -> "
              f"RMSE {sweep['best_rmse']:.4f}")
        print("  " + "  ".join(f"{lam:.3g}:{e:.4f}" for lam, e in zip(sweep["grid"], sweep["rmse"], strict=True)))
        trade = tradeoff(profile, targets, take.valid, truth, rig.names, take.rate, tj)
        print("jitter / lag / blink trade-off of the robust mode's weight filter "
              "(1€ min_cutoff Hz, beta; IMM move-model acceleration sd /s^2):")
        for r in trade:
            print(f"  {r['filter']:22s} jitter {r['jitter_ratio']:7.2f} x  lag {r['lag']:5.2f} fr  "
                  f"blink {percent(r['blink']):>4s}  RMSE {r['rmse']:.4f}")
    if args.plot:
        plot(args.plot, rig.names, truth, curves, take.rate)
        print(f"plot: {args.plot}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"settings": vars(s), "selected": tuned, "rows": [vars(r) for r in rows],
                                               "summary": {k: v for k, v in summary.items() if k != "lines"},
                                               "sweep": sweep, "tradeoff": trade}, indent=1, default=float))
    return 0


def summarise(rows: list[Row]) -> dict:
    """Baseline (plain lsq), the best streaming mode by RMSE among those with <= 1 frame lag, and the checks."""
    base = next((r for r in rows if r.mode == "lsq"), None)
    fast = [r for r in rows if r.kind == "streaming" and r.lag <= 1.0]
    best = min(fast, key=lambda r: r.rmse) if fast else None
    out: dict = {"lines": []}
    if base and best:
        out.update(baseline=base.mode, best_streaming=best.mode, rmse_ratio=best.rmse / base.rmse)
        out["lines"].append(
            f"best streaming (lag <= 1 frame): {best.mode}: RMSE {best.rmse:.4f} = {best.rmse / base.rmse:.2f} x lsq; "
            f"jitter {best.jitter_ratio:.2f} x truth; lag {best.lag:.2f} frames; blinks {percent(best.blink)}")
    smooth = [r for r in rows if r.kind == "streaming" and r.jitter_ratio <= 1.5]
    if smooth:
        r = min(smooth, key=lambda r: r.lag)
        out["lines"].append(f"least lag with jitter <= 1.5 x truth: {r.mode}: lag {r.lag:.2f} frames, "
                            f"RMSE {r.rmse:.4f}")
    else:
        out["lines"].append("no streaming mode reaches jitter <= 1.5 x truth")
    return out


def ridge_sweep(profile, targets, valid, truth, selected: float, rate: float) -> dict:
    """RMSE of the robust mode over a grid of its sparse fit's ridge, to place the selected value."""
    grid = sorted({float(g) for g in SPARSE_GRID} | {float(selected)})
    rmse = []
    for lam in grid:
        W, _ = run_solver(robust_solver(profile, {"ridge": lam, "rate": rate}), targets, valid, True)
        rmse.append(weight_rmse(W, truth))
    i = int(np.argmin(rmse))
    return {"grid": grid, "rmse": rmse, "best_ridge": grid[i], "best_rmse": rmse[i],
            "selected": float(selected), "selected_rmse": rmse[grid.index(float(selected))]}


TRADE_FILTERS = [None, ("1e", 1.0, 100.0), ("1e", 1.0, 30.0), ("1e", 1.0, 10.0), ("1e", 0.5, 10.0),
                 ("1e", 0.25, 3.0), ("1e", 0.1, 1.0), ("1e", 0.05, 0.0),
                 ("imm", 160.0), ("imm", 80.0), ("imm", 40.0), ("imm", 20.0), ("imm", 10.0),
                 ("imm", 640.0, "marginal"), ("imm", 320.0, "marginal")]


def tradeoff(profile, targets, valid, truth, names, rate: float, truth_jitter: float) -> list[dict]:
    """The robust mode with weaker to stronger weight filters: 1€ (min_cutoff Hz, beta) and the IMM
    ('move' model acceleration sd, weight units / s^2): how far jitter falls for how much lag and
    blink amplitude (the causal marker filter and sparse fit run once; the filters after)."""
    s = robust_settings(profile, {"rate": rate})
    markers = marker_filter(rate, float(s.marker_window))
    fit = FilteredSolver(sparse_fit(profile, {"rate": rate}, markers.noise_gain), marker_filter=markers)
    W0, _ = run_solver(fit, targets, valid, True)
    out = []
    for f in TRADE_FILTERS:
        if f is None:
            W, label = W0, "none"
        elif f[0] == "1e":
            W, label = OneEuroFilter(rate, f[1], f[2], 1.0).filter(W0), f"1e {f[1]:g} Hz, {f[2]:g}"
        else:
            noise = f[2] if len(f) > 2 else "fit"
            imm = imm_filter(profile, {"rate": rate, "move_accel": f[1], "weight_noise": noise}, markers.noise_gain)
            W, label = imm.filter(W0), f"imm move {f[1]:g}" + ("" if noise == "fit" else f" {noise}")
        W = np.clip(W, profile.lower, profile.upper)
        out.append({"filter": label, "jitter_ratio": jitter(W) / truth_jitter, "lag": lag_frames(W, truth),
                    "blink": blink_amplitude(W, truth, names), "rmse": weight_rmse(W, truth)})
    return out


def plot(path: str, names: list[str], truth: np.ndarray, curves: dict[str, np.ndarray], rate: float) -> None:
    """A few weight curves (blink, jaw, smile, most active other) against the truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    picks = []
    for key in ("blink", "jawopen", "smile"):
        k = next((i for i, n in enumerate(names) if key in n.lower()), None)
        if k is not None and k not in picks:
            picks.append(k)
    for k in np.argsort(-truth.std(0)):
        if len(picks) >= 4:
            break
        if int(k) not in picks:
            picks.append(int(k))
    shown = [n for n in ("lsq", "robust", "robust-lag") if n in curves] or list(curves)[:3]
    t = np.arange(len(truth)) / rate
    fig, axes = plt.subplots(len(picks), 1, figsize=(11, 2.2 * len(picks)), sharex=True)
    for ax, k in zip(np.atleast_1d(axes), picks, strict=False):
        ax.plot(t, truth[:, k], "k", lw=2, label="truth")
        for name in shown:
            ax.plot(t, curves[name][:, k], lw=0.8, label=name)
        ax.set_ylabel(names[k], fontsize=8)
    np.atleast_1d(axes)[0].legend(loc="upper right", fontsize=8, ncol=len(shown) + 1)
    np.atleast_1d(axes)[-1].set_xlabel("seconds")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
