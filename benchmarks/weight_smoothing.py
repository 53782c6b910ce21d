"""Offline weight-curve smoothing: the l1 trend filter (solvers/trend.py) against the centred quartic
Savitzky-Golay smoother it replaced, on the bundled demo take's noise-robust movement solve before
any weight smoothing (ground truth beside the take): time per take, ADMM iterations, jitter ratio,
weight RMSE and blink amplitude; and the trend filter's time as the take gets longer (O(T) per
iteration).

    python -m benchmarks.weight_smoothing [--quick]

``run(quick)`` prints a table and returns the figures as a dict (``--json FILE`` writes them).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from benchmarks.demo_take import demo_take
from benchmarks.timing import suite_main
from solvers.filters import FixedLagSmoother
from solvers.trend import TrendFilter

MULTIPLES = (5.0, 10.0, 20.0)
QUARTIC_LAG = 12  # the replaced smoother: centred quartic over 25 frames


def _raw_solve():
    """The demo take's noise-robust movement solve with the weight smoothing off, its truth, the
    penalty of one weight-noise sd per shape (the unit the trend multiple is in), and the take."""
    from livecap.modes.movement import build_movement

    d = demo_take()
    W = build_movement(d.profile, {"trend": 0}).solve(d.targets, d.valid)
    unit = build_movement(d.profile, {"trend": 1.0}).trend.lam
    return W, unit, d


def _timed(fn, repeats: int):
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def run(quick: bool = False) -> dict:
    from livecap.cli.noise_study import blink_amplitude
    from livecap.offline.metrics import jitter, weight_rmse

    W, unit, d = _raw_solve()
    truth, names, lower, upper = d.truth, d.names, d.profile.lower, d.profile.upper
    repeats = 1 if quick else 3
    tj = jitter(truth)

    def row(label: str, smoothed: np.ndarray, seconds: float, iterations: int | None) -> dict:
        S = np.clip(smoothed, lower, upper)
        return {"smoother": label, "seconds": seconds, "iterations": iterations, "jitter_ratio": jitter(S) / tj,
                "rmse": weight_rmse(S, truth), "blink": blink_amplitude(S, truth, names)}

    quartic = FixedLagSmoother(QUARTIC_LAG, order=4)
    S, sec = _timed(lambda: quartic.filter(W), repeats)
    rows = [row("none", W, 0.0, None), row("quartic over 25 frames (before)", S, sec, None)]
    base = sec
    for multiple in MULTIPLES[1:2] if quick else MULTIPLES:
        tf = TrendFilter(multiple * unit)
        S, sec = _timed(lambda tf=tf: tf.filter(W), repeats)
        rows.append(row(f"trend filter {multiple:g} sd", S, sec, tf.iterations))
    print(f"demo take: {len(W)} frames, {W.shape[1]} shapes ({int(np.any(W != 0, axis=0).sum())} ever active); "
          f"best of {repeats}")
    print(f"{'smoother':>32} {'seconds':>8} {'x quartic':>10} {'ADMM it':>8} {'jitter x':>9} {'RMSE':>7} {'blink':>6}")
    for r in rows:
        ratio = r["seconds"] / base if r["seconds"] else float("nan")
        r["time_ratio"] = ratio
        print(f"{r['smoother']:>32} {r['seconds']:>8.3f} {ratio:>10.1f} {str(r['iterations'] or '-'):>8} "
              f"{r['jitter_ratio']:>9.2f} {r['rmse']:>7.4f} {r['blink']:>6.2f}")

    scaling = []
    tf = TrendFilter(10.0 * unit)
    print(f"\ntrend filter 10 sd on the take repeated end to end: {'frames':>7} {'seconds':>8} {'ms/frame':>9}")
    for copies in ((1, 2) if quick else (1, 2, 4)):
        Wn = np.tile(W, (copies, 1))
        _, sec = _timed(lambda Wn=Wn: tf.filter(Wn), 1)
        scaling.append({"frames": len(Wn), "seconds": sec, "ms_per_frame": sec * 1e3 / len(Wn),
                        "iterations": tf.iterations})
        print(f"{'':>50} {len(Wn):>7d} {sec:>8.3f} {sec * 1e3 / len(Wn):>9.3f}")
    return {"frames": len(W), "shapes": int(W.shape[1]), "repeats": repeats, "rows": rows, "scaling": scaling}


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__))
