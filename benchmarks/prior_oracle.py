"""The prior's form against its strength, in hindsight (issue 41.2): how far can one strength per take, or one
strength per band of directions, bring ICT's offline ``kalman`` RMSE with a prior?

Leave one file out over ../shared/realdata/performance (the prior from the other files, as ``livecap realeval``
builds it), each take solved offline by ``kalman`` as ``livecap solve`` does, its prior checked against the take as
today. Rows per take, weight RMSE x the oracle's:

- ``chosen``: the strength ``take_strength`` picks (today's code);
- ``scalar``: the best of the 9 grid strengths (``marker_kalman.STRENGTHS``) in hindsight;
- ``bands``: the checked prior's precision P split along the generalised eigen-directions of (P, B'B) -- L^-1 P L^-T
  = Q diag(d) Q' for B'B = L L' (Golub & Van Loan 2013 §8.7), d the prior's precision over the markers' information
  per direction, so a large d is a direction the markers see weakly -- into ``--bands`` equal-count bands by d, and
  each band's strength picked from the same grid in hindsight by coordinate descent from the best scalar
  (``--sweeps`` passes over the bands).

``--mean`` / ``--cov`` swap the checked prior's mean / covariance for the take's own no-prior fit's (no truth), a
pooled or noise-corrected form of it, or the take's true ones (ceilings); ``--extend`` adds strengths to the grid.
The truth picks every hindsight choice: these rows bound what a criterion choosing that form could reach; they are
not a mode.

    python -m benchmarks.prior_oracle [--noise 0.5 0.2] [--seconds 10] [--bands 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np


def band_precisions(basis: np.ndarray, precision: np.ndarray, bands: int) -> tuple[list[np.ndarray], np.ndarray]:
    """P = sum_b P_b, each P_b the prior's precision along one band of generalised eigen-directions of (P, B'B),
    the bands equal in count, ordered from the directions the markers see best (small d) to the weakest; and d."""
    G = basis.T @ basis
    m = len(G)
    L = np.linalg.cholesky(G + 1e-12 * np.trace(G) / m * np.eye(m))
    Li = np.linalg.solve(L, np.eye(m))
    d, Q = np.linalg.eigh(Li @ precision @ Li.T)
    Minv = Q.T @ L.T  # M = L^-T Q, M' G M = I, M' P M = diag(d): P = M^-T diag(d) M^-1
    parts = np.array_split(np.arange(m), bands)
    return [Minv[idx].T @ (np.maximum(d[idx], 0.0)[:, None] * Minv[idx]) for idx in parts], d


def denoised(C: np.ndarray, basis: np.ndarray, noise_mm: float, floor: float = 1e-2) -> np.ndarray:
    """A fit's weight covariance less the per-frame fit noise N = noise^2 (B'B)^-1: in N's whitened coordinates
    its eigenvalues minus 1, kept at least ``floor`` (the moment estimate of the signal's covariance)."""
    G = basis.T @ basis
    m = len(G)
    N = noise_mm**2 * np.linalg.inv(G + 1e-9 * np.trace(G) / m * np.eye(m))
    L = np.linalg.cholesky(N)
    Li = np.linalg.solve(L, np.eye(m))
    lam, V = np.linalg.eigh(Li @ C @ Li.T)
    S = L @ V
    return (S * np.maximum(lam - 1.0, floor)) @ S.T


def main(argv: list[str] | None = None) -> int:
    from livecap.calibration.animation_prior import build_prior
    from livecap.cli.realeval import _realdata, _rig
    from livecap.demo.curves_take import CurveTakeSettings, curves_take
    from livecap.modes import marker_kalman
    from livecap.modes.registry import build_solver
    from livecap.offline.metrics import weight_rmse
    from livecap.offline.real_eval import oracle_weights, plain_profile
    from livecap.offline.solve import solve_take
    from transport.llf_csv import read_llf_csv

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--noise", type=float, nargs="+", default=[0.5, 0.2])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--start", type=float, default=10.0)
    p.add_argument("--occlusion", type=float, default=0.05)
    p.add_argument("--bands", type=int, default=3)
    p.add_argument("--sweeps", type=int, default=1)
    p.add_argument("--files", nargs="+", help="held-out files by name (default: all six)")
    p.add_argument("--mean", choices=["checked", "self", "truth"], default="checked",
                   help="the prior's mean: today's check against the take; the take's own no-prior kalman fit's mean "
                        "(offline, no truth); the take's true mean (a ceiling, not a criterion)")
    p.add_argument("--cov", choices=["checked", "self", "pooled", "denoised", "truth"], default="checked",
                   help="the prior's covariance: today's; the take's own no-prior kalman fit's (offline, no truth); "
                        "the mean of that and the others' (pooled); the own fit's less its per-frame noise "
                        "noise^2 (B'B)^-1 (denoised); the take's true weights' (a ceiling)")
    p.add_argument("--extend", type=float, nargs="*", default=[],
                   help="strengths added to the grid (also offered to today's criterion): is the grid's end the limit?")
    p.add_argument("--json")
    args = p.parse_args(argv)
    logging.getLogger("livecap").setLevel(logging.ERROR)  # the check's warnings, once per solve

    grid0 = marker_kalman.STRENGTHS
    grid = marker_kalman.STRENGTHS = np.unique(np.concatenate([grid0, args.extend]))
    unit = int(np.argmin(np.abs(grid - 1.0)))  # banded fits run at strength 1, the bands carrying the grid's values
    take_strength, use_support = marker_kalman.take_strength, marker_kalman.MarkerKalmanSolver._use_support
    state: dict = {"fixed": None, "scales": None, "chosen": None, "mean": None, "precision": None}

    def fixed_strength(*a, **k):
        best, err, used = take_strength(*a, **k)
        state["chosen"] = best
        return (best if state["fixed"] is None else state["fixed"]), err, used

    def banded_support(self, s, frames, built=None):
        use_support(self, s, frames, built)
        if state["mean"] is not None:
            self.mean = state["mean"]
        if state["precision"] is not None:
            self.precision = state["precision"]
        if state["scales"] is not None:
            parts, _ = band_precisions(self.profile.basis, self.precision, len(state["scales"]))
            self.precision = sum(c * Pb for c, Pb in zip(state["scales"], parts, strict=True))
        if any(state[k] is not None for k in ("mean", "precision", "scales")):
            self.joint = self.pose.augment(self.profile.basis, self.lower, self.upper, self.mean, self.precision)
            self._fits, self._spreads, self._along = {}, {}, {}

    files = sorted((_realdata() / "performance").glob("*.csv"))
    rig, layout = _rig("ict")
    out = []
    marker_kalman.take_strength = fixed_strength
    marker_kalman.MarkerKalmanSolver._use_support = banded_support
    try:
        for noise in args.noise:
            for f in files:
                if args.files and f.stem not in args.files:
                    continue
                t0 = time.perf_counter()
                length = read_llf_csv(f).times[-1]
                start = max(0.0, min(args.start, length - args.seconds))
                ct = curves_take(rig, layout, f, CurveTakeSettings(start=start, seconds=args.seconds, noise_mm=noise,
                                                                  occlusion=args.occlusion))
                oracle = weight_rmse(oracle_weights(ct, rig.lower, rig.upper), ct.weights)
                profile = plain_profile(rig, layout, ct)
                profile.prior = build_prior([o for o in files if o != f], rig.names, rig.lower, rig.upper)
                opts = {"rate": ct.take.rate}
                state["mean"] = state["precision"] = state["scales"] = state["fixed"] = None
                if "self" in (args.mean, args.cov) or args.cov in ("pooled", "denoised"):
                    bare = plain_profile(rig, layout, ct)
                    fit = build_solver("kalman", bare, opts)
                    own = solve_take(ct.take, bare, fit).weights
                if args.mean == "self":
                    state["mean"] = own.mean(0)
                elif args.mean == "truth":
                    state["mean"] = ct.weights.mean(0)
                if args.cov != "checked":
                    C = np.cov((ct.weights if args.cov == "truth" else own).T)
                    if args.cov == "pooled":
                        C = 0.5 * (C + profile.prior.cov)
                    elif args.cov == "denoised":
                        C = denoised(C, bare.basis, fit.chosen["noise_mm"])
                    state["precision"] = np.linalg.inv(C + 1e-6 * np.trace(C) / len(C) * np.eye(len(C)))

                def ratio(fixed, scales=None, profile=profile, opts=opts, ct=ct, oracle=oracle):
                    state["fixed"], state["scales"] = fixed, scales
                    W = solve_take(ct.take, profile, build_solver("kalman", profile, opts)).weights
                    return weight_rmse(W, ct.weights) / oracle

                chosen = ratio(None)
                k_chosen = state["chosen"]
                scalar = [ratio(k) for k in range(len(grid))]
                k_best = int(np.argmin(scalar))
                _, d = band_precisions(profile.basis, np.linalg.inv(profile.prior.cov), args.bands)
                ks = [k_best] * args.bands
                best = scalar[k_best]
                for _ in range(args.sweeps):
                    for b in range(args.bands):
                        for k in range(len(grid)):
                            if k == ks[b]:
                                continue
                            trial = ks.copy()
                            trial[b] = k
                            r = ratio(unit, [grid[j] for j in trial])
                            if r < best:
                                best, ks = r, trial
                rec = {"noise_mm": noise, "mean": args.mean, "cov": args.cov, "file": f.stem, "oracle_rmse": oracle,
                       "chosen_x": chosen,
                       "chosen_strength": float(grid[k_chosen]), "scalar_x": scalar,
                       "best_scalar_x": scalar[k_best], "best_scalar": float(grid[k_best]), "bands_x": best,
                       "band_strengths": [float(grid[j]) for j in ks],
                       "d_quantiles": np.quantile(d, [0, 0.25, 0.5, 0.75, 1]).tolist()}
                out.append(rec)
                print(f"{noise:g} mm {f.stem:32s} chosen {chosen:.3f} ({grid[k_chosen]:.3g})  "
                      f"scalar {scalar[k_best]:.3f} "
                      f"({grid[k_best]:.3g})  bands {best:.3f} {[f'{grid[j]:.3g}' for j in ks]}  "
                      f"[{time.perf_counter() - t0:.0f} s]", flush=True)
    finally:
        marker_kalman.take_strength = take_strength
        marker_kalman.STRENGTHS = grid0
        marker_kalman.MarkerKalmanSolver._use_support = use_support
    for noise in args.noise:
        rows = [r for r in out if r["noise_mm"] == noise]
        print(f"{noise:g} mm mean: chosen {np.mean([r['chosen_x'] for r in rows]):.3f}  scalar "
              f"{np.mean([r['best_scalar_x'] for r in rows]):.3f}  bands {np.mean([r['bands_x'] for r in rows]):.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
                                               "loadavg": os.getloadavg(), "args": vars(args), "rows": out},
                                              indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
