"""``livecap fig11``: reproduce Seol et al. 2012 Fig. 11 on a take (the bundled demo by default).

Velocity error |D(BW)^T - DS^T|_F^2 of constrained solves, over the unconstrained per-frame solve
("No Const"): per-frame hard range -0.5 <= w <= 1.5 ("Range PF"), per-frame PCA prior
("Prior PF"), and movement matching with the prior (§4-5). As in Seol §7, each alpha is the
smallest that keeps that method's weights inside the Range PF range (found by bisection), so
all constrained methods have the same weight range. Writes a Markdown table, the per-frame
errors as CSV and a PNG plot (total error per method; extra error along time).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from livecap.cli.common import load_rig, profile_for
from livecap.demo import DEMO_RIG, DEMO_TAKE
from livecap.metrics import range_excess, velocity_error_per_frame
from livecap.solve import prepare_targets
from solvers.movement import MovementMatching
from solvers.per_frame import no_const, prior_pf, range_pf
from solvers.prior import PCAPrior
from transport.takefile import read_take

RECORDINGS = Path(__file__).resolve().parents[2] / "recordings"


def register(sub) -> None:
    p = sub.add_parser("fig11", help="reproduce Seol 2012 Fig. 11: extra velocity error of constrained solves",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--take", default=str(RECORDINGS / DEMO_TAKE), help="take (default: the demo take)")
    p.add_argument("--rig", default=str(RECORDINGS / DEMO_RIG), help="rig (default: the demo rig)")
    p.add_argument("--markers", help="markers.json (default: beside the rig)")
    p.add_argument("--profile", help="calibrated profile (default: calibrate on the take's first second)")
    p.add_argument("--neutral-seconds", type=float, default=1.0)
    p.add_argument("--range", nargs=2, type=float, default=[-0.5, 1.5], metavar=("LO", "HI"),
                   help="Range PF limits and the weight range every alpha is fitted to (default -0.5 1.5)")
    p.add_argument("--alpha-pf", type=float, help="Prior PF alpha (default: fitted to the range)")
    p.add_argument("--alpha-mm", type=float, help="movement-matching alpha (default: fitted to the range)")
    p.add_argument("--out-dir", default="out/fig11", help="where fig11.md, fig11.csv and fig11.png go")
    p.set_defaults(func=run)


def fit_alpha(solve, lo: float, hi: float, tol: float = 0.005, steps: int = 16) -> tuple[float, np.ndarray]:
    """Smallest alpha (log-bisection in [1e-4, 1e4]) whose weights stay inside [lo, hi] (+tol)."""
    a, b = 1e-4, 1e4
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
            alpha_pf: float | None = None, alpha_mm: float | None = None) -> dict:
    """Weights, alphas, per-frame velocity errors and timings of the four methods."""
    prior = PCAPrior.from_shapes(basis)
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

    for name, fn, given in (("Prior PF", pf, alpha_pf), ("Movement + prior", mm, alpha_mm)):
        t0 = time.perf_counter()
        a, W = (given, fn(given)) if given is not None else fit_alpha(fn, lo, hi)
        out["seconds"][name] = time.perf_counter() - t0
        out["weights"][name], out["alpha"][name] = W, a
    out["velocity"] = {k: velocity_error_per_frame(basis, W, targets, valid) for k, W in out["weights"].items()}
    return out


def table(result: dict, lo: float, hi: float) -> str:
    base = result["velocity"]["No Const"].sum()
    lines = ["| method | alpha | weight range | velocity error (mm^2) | extra over No Const |",
             "|---|---|---|---|---|"]
    for name, v in result["velocity"].items():
        W = result["weights"][name]
        a = result["alpha"].get(name)
        lines.append(f"| {name} | {'' if a is None else f'{a:.4g}'} | [{W.min():.2f}, {W.max():.2f}] | "
                     f"{v.sum():.0f} | {v.sum() - base:+.0f} ({(v.sum() - base) / base * 100:+.1f}%) |")
    lines.append(f"\nConstrained weight range [{lo:g}, {hi:g}]; alphas fitted to it (Seol et al. 2012 §7).")
    return "\n".join(lines)


def plot(result: dict, rate: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    v = result["velocity"]
    base = v["No Const"]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw={"width_ratios": [1, 2.4]})
    names = list(v)
    colors = {"No Const": "0.5", "Range PF": "tab:orange", "Prior PF": "tab:green", "Movement + prior": "tab:blue"}
    ax1.bar(range(len(names)), [v[n].sum() for n in names], color=[colors.get(n, "k") for n in names])
    ax1.set_xticks(range(len(names)), [n.replace(" + ", "\n+ ") for n in names], fontsize=8)
    ax1.set_ylabel("sum of velocity errors (mm²)")
    ax1.set_title("(a) velocity error")
    k = max(1, int(round(rate * 0.25)))
    t = np.arange(len(base)) / rate
    for n in names[1:]:
        d = np.convolve(v[n] - base, np.ones(k) / k, mode="same")
        ax2.plot(t, d, color=colors.get(n, "k"), ls="-" if n.startswith("Movement") else ":", lw=1.2, label=n)
    ax2.axhline(0, color="0.6", lw=0.8)
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("extra velocity error per frame (mm², 0.25 s mean)")
    ax2.set_title("(b) delta from No Const along the take")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    rig, layout = load_rig(args)
    take = read_take(args.take)
    profile = profile_for(args, rig, layout, take)
    take_sel, targets, _, _ = prepare_targets(take, profile)
    lo, hi = args.range
    result = compare(profile.basis, targets, take_sel.valid, lo, hi, args.alpha_pf, args.alpha_mm)
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    text = table(result, lo, hi)
    (out / "fig11.md").write_text(f"# Seol et al. 2012 Fig. 11 on {Path(args.take).name}\n\n{text}\n")
    names = list(result["velocity"])
    np.savetxt(out / "fig11.csv", np.column_stack([np.arange(take.n_frames)] + [result["velocity"][n] for n in names]),
               delimiter=",", header="frame," + ",".join(names), comments="", fmt="%.6g")
    plot(result, take.rate, out / "fig11.png")
    print(text)
    print(f"wrote {out / 'fig11.md'}, {out / 'fig11.csv'}, {out / 'fig11.png'}")
    return 0
