"""``livecap fig11``: Seol et al. 2012 Fig. 11, the extra velocity error that constraints cost.

Velocity error |D(BW)^T - DS^T|_F^2 (Seol §7) of constrained solves, over the unconstrained
per-frame solve ("No Const"): per-frame hard range -0.5 <= w <= 1.5 ("Range PF"), per-frame PCA
prior ("Prior PF"), and movement matching with the prior (§4-5) in two forms:

* "Movement + prior, bounded": constraints active, as in Seol's Figs. 3 and 11: the same range
  as hard limits of the spacetime solve (solvers/bounded.py) with a small prior weight, Seol's
  alpha = 0.01 (§5, Fig. 7f, §7). Seol §7 pick each alpha "to produce the same weight range
  used for Range PF"; with the range a constraint that holds for any alpha, so the prior keeps
  the value Seol found to work for movement matching (--alpha-bound changes it).
* "Movement + prior, soft": no limits; alpha fitted so the prior alone brings the weights into
  the range (the smallest such alpha, bisection on log alpha), as is Prior PF's.

Writes a Markdown table, the per-frame errors as CSV and a PNG: (a) total error per method,
(b) extra error over No Const along time.

Default: Seol's setting, retargeting onto a different character that cannot reproduce the
source (livecap.demo.retarget: an actor performing demo_rig(0), target demo_rig(3) reduced to 33
shapes, calibrated with the RBF warp), once with the demo take's marker noise and once
noise-free. With --take and/or --rig: your own take and rig (the other defaults to the demo's).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from livecap.cli.common import load_rig, profile_for
from livecap.demo import DEMO_RIG, DEMO_TAKE
from livecap.offline.metrics import range_excess, velocity_error_per_frame
from livecap.offline.solve import prepare_targets
from solvers.movement import MovementMatching
from solvers.per_frame import no_const, prior_pf, range_pf
from solvers.prior import PCAPrior
from transport.takefile import read_take

RECORDINGS = Path(__file__).resolve().parents[2] / "recordings"
TOL = 0.005  # how far past the range a fitted alpha's weights may go (the bisection's target)
ALPHA_BOUND = 0.01  # Seol et al. 2012 §5 (Fig. 7f) and §7: the movement-matching prior weight
BOUNDED, SOFT = "Movement + prior, bounded", "Movement + prior, soft"


def register(sub) -> None:
    p = sub.add_parser("fig11", help="reproduce Seol 2012 Fig. 11: extra velocity error of constrained solves",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--take", help=f"your take (default: the retargeting scenario; with --rig only: {DEMO_TAKE})")
    p.add_argument("--rig", help=f"your rig (default: the retargeting scenario; with --take only: {DEMO_RIG})")
    p.add_argument("--markers", help="markers.json (default: beside the rig)")
    p.add_argument("--profile", help="calibrated profile (default: calibrate on the take's first second)")
    p.add_argument("--neutral-seconds", type=float, default=1.0,
                   help="neutral span at the start of --take when no --profile (default 1)")
    g = p.add_argument_group("retargeting scenario (without --take/--rig)")
    g.add_argument("--seconds", type=float, default=20.0, help="length of the performance (default 20)")
    g.add_argument("--rate", type=float, default=120.0, help="capture rate in Hz (default 120)")
    g.add_argument("--noise-mm", dest="noise_levels", type=float, nargs="+", default=[0.5, 0.0],
                   help="marker noise levels, one variant each (default: 0.5 as the demo take, and 0)")
    g.add_argument("--occlusion", type=float, default=0.02,
                   help="fraction of marker-frames missing, in bursts (default 0.02 as the demo take)")
    g.add_argument("--target-shapes", type=int, default=33, help="shapes kept in the target rig (default 33)")
    g.add_argument("--target-seed", type=int, default=3, help="target character demo_rig(seed) (default 3)")
    g.add_argument("--subset-seed", type=int, default=11, help="which shapes the target keeps (default 11)")
    g.add_argument("--source-seed", type=int, default=0, help="source character demo_rig(seed) (default 0)")
    g.add_argument("--performance-seed", type=int, default=1, help="the source performance (default 1)")
    p.add_argument("--range", nargs=2, type=float, default=[-0.5, 1.5], metavar=("LO", "HI"),
                   help="Range PF limits and the weight range every alpha is fitted to (default -0.5 1.5)")
    p.add_argument("--alpha-pf", type=float, help="Prior PF alpha (default: fitted to the range)")
    p.add_argument("--alpha-mm", type=float, help="soft movement-matching alpha (default: fitted to the range)")
    p.add_argument("--alpha-bound", type=float, default=ALPHA_BOUND,
                   help=f"bounded movement-matching alpha (default {ALPHA_BOUND:g}, Seol §5/§7)")
    p.add_argument("--out-dir", default="out/fig11", help="where fig11.md, fig11*.csv and fig11.png go")
    p.set_defaults(func=run)


def fit_alpha(solve, lo: float, hi: float, tol: float = TOL, steps: int = 24,
              bounds: tuple[float, float] = (1e-4, 1e4)) -> tuple[float, np.ndarray]:
    """Smallest alpha whose weights stay inside [lo, hi] (+tol): Seol §7's rule that every
    constrained method produce the Range PF weight range. Bisection on log alpha within
    ``bounds`` (deterministic; the weight range shrinks monotonically with alpha for a prior
    centred inside the range). When even the upper bound does not reach the range, that
    alpha and its (out-of-range) weights are returned; callers report the range reached."""
    a, b = bounds
    W = solve(a)
    if range_excess(W, lo, hi) <= tol:
        return a, W
    Wb = solve(b)
    for _ in range(steps):
        mid = np.sqrt(a * b)
        Wm = solve(mid)
        if range_excess(Wm, lo, hi) <= tol:
            b, Wb = mid, Wm
        else:
            a = mid
    return b, Wb


def compare(basis: np.ndarray, targets: np.ndarray, valid: np.ndarray, lo: float, hi: float,
            alpha_pf: float | None = None, alpha_mm: float | None = None, prior: PCAPrior | None = None,
            alpha_bound: float = ALPHA_BOUND, soft: bool = True) -> dict:
    """Weights, alphas, per-frame velocity errors and timings of the methods (``soft``: include
    the soft-prior movement solve, whose alpha fit costs ~25 solves).

    ``prior`` defaults to Seol §7's: all the target's blendshapes as training examples (plus
    the neutral, see :meth:`solvers.prior.PCAPrior.from_shapes`).
    """
    prior = prior or PCAPrior.from_shapes(basis)
    out: dict = {"weights": {}, "alpha": {}, "seconds": {}}
    t0 = time.perf_counter()
    out["weights"]["No Const"] = no_const(basis, targets, valid)
    out["seconds"]["No Const"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    out["weights"]["Range PF"] = range_pf(basis, targets, valid, lo, hi)
    out["seconds"]["Range PF"] = time.perf_counter() - t0

    def pf(a):
        return prior_pf(basis, targets, valid, prior, a)

    def mm(a):
        return MovementMatching(basis, alpha=a, prior=prior).solve(targets, valid)

    m = basis.shape[1]
    t0 = time.perf_counter()
    bounded = MovementMatching(basis, np.full(m, lo), np.full(m, hi), alpha=alpha_bound,
                               prior=prior if alpha_bound > 0 else None, limits="bound")
    out["weights"][BOUNDED] = bounded.solve(targets, valid)
    out["seconds"][BOUNDED] = time.perf_counter() - t0
    out["alpha"][BOUNDED] = alpha_bound
    out["admm"] = bounded.bounded_info
    methods = [("Prior PF", pf, alpha_pf)] + ([(SOFT, mm, alpha_mm)] if soft else [])
    for name, fn, given in methods:
        t0 = time.perf_counter()
        a, W = (given, fn(given)) if given is not None else fit_alpha(fn, lo, hi)
        out["seconds"][name] = time.perf_counter() - t0
        out["weights"][name], out["alpha"][name] = W, a
    out["velocity"] = {k: velocity_error_per_frame(basis, W, targets, valid) for k, W in out["weights"].items()}
    return out


def extra(result: dict) -> dict[str, float]:
    """Additional velocity error of each method over No Const (Fig. 11's quantity), summed."""
    base = result["velocity"]["No Const"].sum()
    return {k: float(v.sum() - base) for k, v in result["velocity"].items()}


def table(result: dict, lo: float, hi: float) -> str:
    base = result["velocity"]["No Const"].sum()
    lines = ["| method | alpha | weight range | velocity error (mm^2) | extra over No Const |",
             "|---|---|---|---|---|"]
    for name, v in result["velocity"].items():
        W = result["weights"][name]
        a = result["alpha"].get(name)
        miss = " (range not reached)" if range_excess(W, lo, hi) > TOL and name != "No Const" else ""
        lines.append(f"| {name} | {'' if a is None else f'{a:.4g}'} | [{W.min():.2f}, {W.max():.2f}]{miss} | "
                     f"{v.sum():.1f} | {v.sum() - base:+.1f} ({(v.sum() - base) / base * 100:+.1f}%) |")
    lines.append(f"\nConstrained weight range [{lo:g}, {hi:g}]: hard limits of Range PF and of the bounded "
                 f"movement solve (alpha {result['alpha'][BOUNDED]:g}, Seol §5/§7); Prior PF's and the soft "
                 "movement solve's alphas fitted to reach it (Seol et al. 2012 §7).")
    info = result.get("admm")
    if info is not None:
        lines.append(f"Bounded solve: ADMM {info.iterations} iterations, converged {info.converged}, "
                     f"{result['seconds'][BOUNDED]:.2f} s.")
    return "\n".join(lines)


COLORS = {"No Const": "0.5", "Range PF": "tab:orange", "Prior PF": "tab:green", BOUNDED: "tab:blue",
          SOFT: "tab:purple"}


def plot(result: dict, rate: float, path: Path, title: str = "") -> None:
    plot_variants([(title, result, rate)], path)


def plot_variants(variants: list[tuple[str, dict, float]], path: Path) -> None:
    """One row per variant: (a) sum of velocity errors per method, (b) extra over No Const in time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(variants), 2, figsize=(12, 4.2 * len(variants)), squeeze=False,
                             gridspec_kw={"width_ratios": [1, 2.4]})
    for (title, result, rate), (ax1, ax2) in zip(variants, axes, strict=True):
        v = result["velocity"]
        base = v["No Const"]
        names = list(v)
        ax1.bar(range(len(names)), [v[n].sum() for n in names], color=[COLORS.get(n, "k") for n in names])
        ax1.set_xticks(range(len(names)), [n.replace(" + ", "\n+ ").replace(", ", ",\n") for n in names],
                       fontsize=7)
        ax1.set_ylabel("sum of velocity errors (mm²)")
        ax1.set_title(f"(a) velocity error{' — ' + title if title else ''}", fontsize=9)
        k = max(1, int(round(rate * 0.25)))
        t = np.arange(len(base)) / rate
        for n in names[1:]:
            d = np.convolve(v[n] - base, np.ones(k) / k, mode="same")
            ax2.plot(t, d, color=COLORS.get(n, "k"), ls="-" if n == BOUNDED else ":", lw=1.2, label=n)
        ax2.axhline(0, color="0.6", lw=0.8)
        ax2.set_xlabel("time (s)")
        ax2.set_ylabel("extra velocity error per frame (mm², 0.25 s mean)")
        ax2.set_title("(b) delta from No Const along the take", fontsize=9)
        ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _variants(args: argparse.Namespace) -> list[tuple[str, str, np.ndarray, np.ndarray, np.ndarray, float]]:
    """(tag, description, basis, targets, valid, rate) per variant to compare."""
    if args.take or args.rig:
        args.take = args.take or str(RECORDINGS / DEMO_TAKE)
        args.rig = args.rig or str(RECORDINGS / DEMO_RIG)
        rig, layout = load_rig(args)
        take = read_take(args.take)
        profile = profile_for(args, rig, layout, take)
        sel, targets, _, _ = prepare_targets(take, profile)
        desc = f"take {Path(args.take).name}, rig {Path(args.rig).name} ({rig.n_shapes} shapes)"
        return [("", desc, profile.basis, targets, sel.valid, take.rate)]
    from livecap.demo.retarget import retarget_scenario

    out = []
    for noise in args.noise_levels:
        sc = retarget_scenario(args.seconds, args.rate, noise, args.occlusion, source_seed=args.source_seed,
                               target_seed=args.target_seed, target_shapes=args.target_shapes,
                               subset_seed=args.subset_seed, performance_seed=args.performance_seed)
        i = sc.info
        desc = (f"retargeting: source {i['source']} -> target {i['target']}; {i['markers']} markers, "
                f"{i['frames']} frames at {i['rate']:g} Hz, marker noise {noise:g} mm, "
                f"{i['occlusion'] * 100:g}% occluded; RBF warp fit {i['warp_fit_rms_mm']:.2g} mm rms")
        out.append((f"noise{noise:g}", desc, sc.basis, sc.targets, sc.valid, sc.rate))
    return out


def run(args: argparse.Namespace) -> int:
    lo, hi = args.range
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    variants = _variants(args)
    doc = ["# Seol et al. 2012 Fig. 11", ""]
    plots, written = [], []
    for tag, desc, basis, targets, valid, rate in variants:
        result = compare(basis, targets, valid, lo, hi, args.alpha_pf, args.alpha_mm, alpha_bound=args.alpha_bound)
        text = table(result, lo, hi)
        doc += [f"## {desc}", "", text, ""]
        names = list(result["velocity"])
        csv = out / (f"fig11_{tag}.csv" if len(variants) > 1 else "fig11.csv")
        np.savetxt(csv, np.column_stack([np.arange(len(targets))] + [result["velocity"][n] for n in names]),
                   delimiter=",", header="frame," + ",".join(names), comments="", fmt="%.6g")
        written.append(csv)
        plots.append((tag or "", result, rate))
        print(f"{desc}\n{text}\n")
    (out / "fig11.md").write_text("\n".join(doc))
    plot_variants(plots, out / "fig11.png")
    print(f"wrote {out / 'fig11.md'}, {', '.join(str(p) for p in written)}, {out / 'fig11.png'}")
    return 0
