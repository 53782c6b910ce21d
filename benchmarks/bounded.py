"""Bounded offline movement matching (solvers/bounded.py): the velocity-error cost of the rig's limits
(none / clip / bound) and the ADMM's time and iterations, on the bundled demo take and on a
synthetic take whose actor goes 20% past the rig (54 markers x 50 shapes, Seol's Table I size).

    python -m benchmarks.bounded [--quick]

``run(quick)`` prints a table and returns the figures as a dict (``--json FILE`` writes them).
"""

from __future__ import annotations

import os
import platform
import sys
import time

import numpy as np

from benchmarks.demo_take import TAKE, demo_take
from benchmarks.timing import suite_main
from livecap.offline.metrics import velocity_error
from solvers.movement import MovementMatching
from solvers.prior import PCAPrior


def _synthetic(seconds: float, rate: float = 120.0, n: int = 54, m: int = 50):
    rng = np.random.default_rng(3)
    T = int(rate * seconds)
    B = rng.normal(scale=2.0, size=(3 * n, m))
    k = np.exp(-0.5 * (np.arange(-40, 41) / 10.0) ** 2)
    X = rng.normal(size=(T + 100, m))
    Y = np.array([np.convolve(X[:, j], k / k.sum(), mode="same") for j in range(m)]).T[50:50 + T]
    truth = np.clip(1.2 * np.clip(0.3 + 3.0 * Y, 0, 1) * (rng.random(m) < 0.4), 0, 1.2)
    truth[0] = truth[-1] = 0
    S = (truth @ B.T).reshape(T, n, 3) + rng.normal(0, 0.3, (T, n, 3))
    valid = rng.random((T, n)) > 0.02
    return B, np.zeros(m), np.ones(m), S, valid, truth


def compare_limits(B, lower, upper, S, valid, truth, alpha: float, beta: float) -> dict:
    """Velocity error, weight RMSE against the ground truth (clipped to the limits: what a rig
    can show), time and ADMM iterations for limits none / clip / bound."""
    prior = PCAPrior.from_shapes(B) if alpha > 0 else None
    out: dict = {}
    for limits in ("none", "clip", "bound"):
        mm = MovementMatching(B, lower, upper, alpha=alpha, prior=prior, beta=beta, limits=limits)
        t0 = time.perf_counter()
        W = mm.solve(S, valid)
        row = {"solve_s": time.perf_counter() - t0, "velocity_error": velocity_error(B, W, S, valid),
               "outside_limits": int(np.sum((W < lower - 1e-9) | (W > upper + 1e-9))),
               "weight_rmse": float(np.sqrt(np.mean((W - np.clip(truth, lower, upper)) ** 2)))}
        if mm.bounded_info is not None:
            row.update(iterations=mm.bounded_info.iterations, converged=mm.bounded_info.converged)
        out[limits] = row
    base = out["none"]["velocity_error"]
    for row in out.values():
        row["extra_percent"] = (row["velocity_error"] - base) / base * 100
    return out


def run(quick: bool = False) -> dict:
    machine = f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} cpus, load {os.getloadavg()[0]:.1f}"
    cases = {f"synthetic {30 if quick else 120} s 54x50": _synthetic(30 if quick else 120)}
    if TAKE.exists():
        d = demo_take()
        cases["demo take"] = d.profile.basis, d.profile.lower, d.profile.upper, d.targets, d.valid, d.truth
    res: dict = {"machine": machine.strip(), "cases": {}}
    print(f"bounded movement matching ({res['machine']})")
    print(f"{'case':>26} {'alpha':>6} {'limits':>6} {'velocity err':>13} {'extra':>8} {'RMSE':>7} {'out':>7} "
          f"{'solve s':>8} {'ADMM it':>8}")
    for name, data in cases.items():
        for alpha in ((1.0,) if quick else (1.0, 0.1)):
            r = compare_limits(*data, alpha=alpha, beta=0.1)
            res["cases"][f"{name}, alpha {alpha:g}"] = r
            for limits, row in r.items():
                print(f"{name:>26} {alpha:>6g} {limits:>6} {row['velocity_error']:>13.1f} "
                      f"{row['extra_percent']:>+7.2f}% {row['weight_rmse']:>7.4f} {row['outside_limits']:>7d} "
                      f"{row['solve_s']:>8.3f} "
                      f"{row.get('iterations', '-'):>8}")
    return res


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__))
