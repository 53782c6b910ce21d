"""Leave one PERFORMER out: is a prior from other performers ever worse than no prior? (issue 41.2)

For each real performance, an ICT take (livecap.demo.curves_take) is solved by ``kalman`` (the default mode with
a prior) several ways, streamed through the live pipeline and offline: with no prior (a ridge), with a prior built
from the files of *other performers only* as given, the same prior checked against the take and widened where
the actor leaves it (solvers.prior_support's variance only, on the first second streamed: the check before
branch prior3), and checked with its mean re-centred on the actor instead, streamed again each time the take
doubles (today's code). "As given" is the prior at its own covariance throughout; the checked variants start, as
the solver does, from twice it until their first check (marker_kalman.UNCHECKED_SPREAD). Each row also gives its
*pull*: the share of its squared error that is a constant per-shape bias.
``--offline``: the offline solve only (as ``livecap solve``), with the diagnoses of S88-001's offline loss
(docs/robustness.md, "Issue 41: S88-001 offline with another performers' prior"): the variants "prior, mean as
given" (checked, its mean not moved) and "prior, no mean spread" (re-centred, the mean's posterior covariance left
out of the precision); ``--strength K`` holds a prior's strength at ``marker_kalman.STRENGTHS[K]``, ``--evidence``
picks it by the frames' marginal likelihood instead of the held-out markers, ``--true-mean NAMES`` sets the checked
mean of those shapes to the take's true mean (a ceiling, not a method).
Performers are the sources' folders (../shared/realdata/performance/README.md): alexdjulin's anim/ (alex_rom_3,
alex_rom_4, S07-001, S88-001), his csv/ (apfel), JMTechArt (MySlate).

Each file's take has its own noise / occlusion / neutral draw as ``livecap realeval`` draws it
(``curves_take.take_seed`` of the name, ``--seed``, the draw index); ``--draws N``: N draws per file.

    python -m benchmarks.prior_lopo [--noise 0.5] [--seconds 10] [--seed 1] [--draws 1] [--json out.json]
    python -m benchmarks.prior_lopo --offline --variants "no prior" "prior re-centred" [--strength K | --evidence]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from solvers.prior_support import evidence_strength

PERFORMERS = {"alex_rom_3": "anim", "alex_rom_4": "anim", "S07-001": "anim", "S88-001": "anim",
              "apfel": "csv", "MySlate_3_Jason_Millers_iPhone": "jmtechart"}


def _as_given(solver, support, frames, built=None) -> None:
    """The check's result set aside: the prior as given (the code before issue 41.2's check)."""
    solver.support = type(support)(support.axes, support.before, support.before, support.noise_var, 0, solver.mean)


def _pull(row) -> float:
    """The share of the squared weight error that is a constant per-shape bias (mean over shapes of the bias squared
    over the RMSE squared): 1 = a constant pull, 0 = noise about the truth."""
    b = np.array(list(row.bias.values()))
    return float(np.mean(b**2) / max(row.rmse**2, 1e-300))


def _top_bias(row, k: int = 4) -> dict[str, float]:
    return dict(sorted(row.bias.items(), key=lambda kv: -abs(kv[1]))[:k])


def _widen_only(solver, targets, valid, noise_mm, tol=1e-2, outside=10.0):
    """The check before branch prior3: the variance only, widened where the frames want 10 x more (a stand-in for
    MarkerKalmanSolver._support; its ``outside`` is that check's own, whatever the caller asks)."""
    from solvers.prior_support import widen_prior

    return widen_prior(solver.profile.basis, solver._mean0, solver.prior_cov, targets, valid, solver.lower,
                       solver.upper, extra=solver.pose.matrix, noise_var=noise_mm**2, recentre=False, outside=10.0,
                       tol=tol)


def _recentre_widen(solver, targets, valid, noise_mm, tol=1e-2, outside=10.0):
    """The mean re-centred, the variance widened as before (a stand-in for MarkerKalmanSolver._support; ``outside``
    fixed at that check's 10)."""
    from solvers.prior_support import widen_prior

    return widen_prior(solver.profile.basis, solver._mean0, solver.prior_cov, targets, valid, solver.lower,
                       solver.upper, extra=solver.pose.matrix, noise_var=noise_mm**2, outside=10.0, tol=tol)


def _mean_as_given(solver, targets, valid, noise_mm, tol=1e-2, outside=np.inf):
    """Checked as today, the prior's own mean kept (the mean's posterior spread kept too)."""
    from solvers.prior_support import widen_prior

    s = widen_prior(solver.profile.basis, solver._mean0, solver.prior_cov, targets, valid, solver.lower,
                    solver.upper, extra=solver.pose.matrix, noise_var=noise_mm**2, tol=tol, outside=outside)
    return type(s)(s.axes, s.before, s.after, s.noise_var, s.iterations, solver._mean0.copy(), s.mean_cov)


def _no_mean_spread(solver, targets, valid, noise_mm, tol=1e-2, outside=np.inf):
    """Re-centred as today, the precision the prior's own (the mean's posterior covariance left out)."""
    from solvers.prior_support import widen_prior

    s = widen_prior(solver.profile.basis, solver._mean0, solver.prior_cov, targets, valid, solver.lower,
                    solver.upper, extra=solver.pose.matrix, noise_var=noise_mm**2, tol=tol, outside=outside)
    return type(s)(s.axes, s.before, s.after, s.noise_var, s.iterations, s.mean, None)


def _offline_rows(rig, layout, ct, prior, opts, strength: int | None, evidence: bool, true_mean: list[str]) -> list:
    """The oracle and ``kalman``'s offline row; a prior's strength held (``strength``) or by the evidence, the checked
    mean of the ``true_mean`` shapes set to the take's (the held-out markers' choice and the one used in
    ``.picks``)."""
    from livecap.modes import marker_kalman
    from livecap.offline.real_eval import oracle_weights, plain_profile, score
    from livecap.offline.solve import solve_take

    chosen, support = marker_kalman.take_strength, marker_kalman.MarkerKalmanSolver._support
    picks: dict = {}

    def take_strength(B, mean, precision, grid, targets, valid, **kw):
        best, err, used = chosen(B, mean, precision, grid, targets, valid, **kw)
        picks["held-out"] = best
        if prior is not None and evidence:
            best = int(np.argmax(evidence_strength(B, mean, precision, grid, targets, valid, len(rig.names))))
        elif prior is not None and strength is not None:
            best = strength
        picks["used"] = best
        return best, err, used

    idx = [rig.names.index(n) for n in true_mean]

    def truth_in(solver, *a, **kw):
        s = support(solver, *a, **kw)
        mu = s.mean.copy()
        mu[idx] = ct.weights[:, idx].mean(0)
        return type(s)(s.axes, s.before, s.after, s.noise_var, s.iterations, mu, s.mean_cov)

    profile = plain_profile(rig, layout, ct)
    profile.prior = prior
    marker_kalman.take_strength = take_strength
    marker_kalman.MarkerKalmanSolver._support = truth_in
    pick = marker_kalman.MarkerKalmanSolver._evidence_pick
    if prior is not None and (strength is not None or evidence):  # the strength given: not the weaker of two
        marker_kalman.MarkerKalmanSolver._evidence_pick = lambda self, *a: len(marker_kalman.STRENGTHS)
    try:
        t0 = time.perf_counter()
        solved = solve_take(ct.take, profile, marker_kalman.kalman_mode(profile, opts["kalman"]))
        row = score("kalman offline", rig, ct, solved.weights, time.perf_counter() - t0)
    finally:
        marker_kalman.take_strength, marker_kalman.MarkerKalmanSolver._support = chosen, support
        marker_kalman.MarkerKalmanSolver._evidence_pick = pick
    row.picks = dict(picks)
    return [score("oracle", rig, ct, oracle_weights(ct, rig.lower, rig.upper), 0.0), row]


def never_worse(rows: list[dict], base: str = "no prior") -> list[str]:
    """Per noise, path and prior variant: in how many (file, draw) its weight RMSE is not above ``base``'s (issue 41:
    a prior from other performers never worse than none), and by how much where it is."""
    runs: dict[tuple, dict[str, float]] = {}
    for r in rows:
        path = r["mode"].rsplit(" ", 1)[-1]
        runs.setdefault((r["noise_mm"], path, r["file"], r.get("draw", 0)), {})[r["prior"]] = r["rmse"]
    lines = []
    for noise, path in dict.fromkeys(k[:2] for k in runs):
        sel = {k: v for k, v in runs.items() if k[:2] == (noise, path) and base in v}
        for variant in dict.fromkeys(n for v in sel.values() for n in v if n != base):
            rel = {k[2:]: v[variant] / v[base] - 1 for k, v in sel.items() if variant in v}
            worse = {k: x for k, x in rel.items() if x > 0}
            lines.append(f"{noise:g} mm {path}: {variant} never worse than {base} in {len(rel) - len(worse)} of "
                         f"{len(rel)} (file, draw)" + "".join(f"; {f} draw {d} {100 * x:+.1f} %"
                                                              for (f, d), x in worse.items()))
    return lines


def main(argv: list[str] | None = None) -> int:
    from livecap.calibration.animation_prior import build_prior
    from livecap.cli.realeval import _realdata, _rig
    from livecap.demo.curves_take import CurveTakeSettings, curves_take, take_seed
    from livecap.modes import marker_kalman
    from livecap.offline.real_eval import evaluate_curve_take
    from transport.llf_csv import read_llf_csv

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--noise", type=float, nargs="+", default=[0.5])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--files", nargs="+", default=list(PERFORMERS))
    p.add_argument("--variants", nargs="+", default=["no prior", "prior as given", "prior widened",
                                                       "prior re-centred"],
                   help="also: 'prior re-centred 1 s' (checked once), 'prior re-centred, widened' (the variance too)")
    p.add_argument("--offline", action="store_true", help="the offline solve only (and the diagnoses below)")
    p.add_argument("--strength", type=int, help="--offline: a prior's strength held at STRENGTHS[K]")
    p.add_argument("--evidence", action="store_true", help="--offline: a prior's strength by the frames' evidence")
    p.add_argument("--true-mean", nargs="+", default=[], help="--offline: these shapes' checked mean set to the truth")
    p.add_argument("--seed", type=int, default=1, help="base seed of the takes' draws (1: realeval's)")
    p.add_argument("--draws", type=int, default=1, help="draws per file (realeval's 0..N-1)")
    p.add_argument("--json")
    args = p.parse_args(argv)
    rig, layout = _rig("ict")
    folder = _realdata() / "performance"
    out = []
    check = marker_kalman.MarkerKalmanSolver._use_support
    support = marker_kalman.MarkerKalmanSolver._support
    growth, spread = marker_kalman.SUPPORT_GROWTH, marker_kalman.UNCHECKED_SPREAD

    for noise in args.noise:
        for name, draw in [(n, d) for n in args.files for d in range(args.draws)]:
            f = folder / f"{name}.csv"
            others = [folder / f"{o}.csv" for o, who in PERFORMERS.items() if who != PERFORMERS[name]]
            start = max(0.0, min(10.0, read_llf_csv(f).times[-1] - args.seconds))
            seed = take_seed(f, args.seed, draw)
            ct = curves_take(rig, layout, f, CurveTakeSettings(start=start, seconds=args.seconds, noise_mm=noise,
                                                                      seed=seed))
            prior = build_prior(others, rig.names, rig.lower, rig.upper)
            opts = {"kalman": {"rate": ct.take.rate}}
            for label, pr, how, recheck in (("no prior", None, None, False), ("prior as given", prior, None, False),
                                            ("prior widened", prior, _widen_only, False),
                                            ("prior re-centred", prior, support, True),
                                            ("prior re-centred 1 s", prior, support, False),
                                            ("prior re-centred, widened", prior, _recentre_widen, True),
                                            ("prior, mean as given", prior, _mean_as_given, True),
                                            ("prior, no mean spread", prior, _no_mean_spread, True)):
                if label not in args.variants:
                    continue
                marker_kalman.SUPPORT_GROWTH = growth if recheck else float("inf")
                marker_kalman.UNCHECKED_SPREAD = spread if how is not None else 1.0
                marker_kalman.MarkerKalmanSolver._use_support = _as_given if how is None else check
                marker_kalman.MarkerKalmanSolver._support = how or support
                t0 = time.perf_counter()
                if args.offline:
                    rows = _offline_rows(rig, layout, ct, pr, opts, args.strength, args.evidence, args.true_mean)
                else:
                    rows = evaluate_curve_take(rig, layout, ct, ["kalman"], opts, pr)
                oracle = rows[0]
                for r in rows[1:]:
                    rec = {"noise_mm": noise, "file": name, "draw": draw, "seed": seed, "prior": label,
                           "mode": r.mode, "rmse": r.rmse,
                           "rmse_x": r.rmse / oracle.rmse, "p95_mm": r.p95_mm, "p95_x": r.p95_mm / oracle.p95_mm,
                           "jitter_x": r.jitter_x, "blink": r.blink, "pull": _pull(r), "bias": _top_bias(r),
                           "strength": getattr(r, "picks", None)}
                    out.append(rec)
                    print(f"{noise:g} mm {name:32s} d{draw} {label:15s} {r.mode:15s} "
                          f"RMSE {r.rmse:.4f} ({rec['rmse_x']:.2f}x) "
                          f"p95 {r.p95_mm:.2f} ({rec['p95_x']:.2f}x) jitter {r.jitter_x:.2f} blink {r.blink:.2f} "
                          f"pull {rec['pull']:.2f} {rec['strength'] or ''} "
                          f"[{time.perf_counter() - t0:.0f} s]", flush=True)
    marker_kalman.MarkerKalmanSolver._use_support = check
    marker_kalman.MarkerKalmanSolver._support = support
    marker_kalman.SUPPORT_GROWTH, marker_kalman.UNCHECKED_SPREAD = growth, spread
    for line in never_worse(out):
        print(line)
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": platform.node(), "date": time.strftime("%Y-%m-%d %H:%M"),
                                               "load": Path("/proc/loadavg").read_text().split()[:3],
                                               "seconds": args.seconds, "argv": sys.argv[1:] if argv is None else argv,
                                               "rows": out}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
