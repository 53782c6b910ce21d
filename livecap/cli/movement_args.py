"""Command-line options of the movement-matching modes, shared by ``solve``, ``edit`` and ``fig11``."""

from __future__ import annotations

import argparse

from livecap.modes.movement import MovementSettings as D
from livecap.modes.robust import RobustSettings
from transport.weights_csv import read_weights_csv


def add_movement_arguments(p: argparse.ArgumentParser, stream: bool = True) -> None:
    g = p.add_argument_group("movement matching (--mode movement, Seol et al. 2012)")
    g.add_argument("--alpha", type=float, help=f"weight of the PCA prior (default {D.alpha}; 0 disables it)")
    g.add_argument("--beta", type=float, help=f"weight of the position (Sobolev) term (default {D.beta})")
    g.add_argument("--prior", help="prior: an animation prior .npz ('livecap prior build'; movement and kalman), "
                   "'profile' (the one 'calibrate --prior' stored), 'shapes' (movement's default: the rig's shapes "
                   "and the neutral), 'none', or a weights CSV of plausible target animation")
    g.add_argument("--prior-threshold", type=float, help="drop PCA eigenvalues below this fraction of the "
                   f"largest (default {D.prior_threshold:g})")
    g.add_argument("--start", choices=["neutral", "free", "fit"], help="boundary at the first frame "
                   f"(default {D.start})")
    g.add_argument("--end", choices=["neutral", "free", "fit"], help=f"boundary at the last frame (default {D.end})")
    g.add_argument("--missing", choices=["fill", "exact"], help="missing markers offline: fill gaps from the "
                   "rig's fit (default, fast) or drop their rows exactly (slower)")
    g.add_argument("--limits", choices=["none", "clip", "bound"], help="rig weight limits: offline 'bound' "
                   "solves with the limits as constraints (ADMM), 'clip' clips the result, 'none' ignores them "
                   "(offline default clip); streaming clips the published frame ('bound' = 'clip' there)")
    g.add_argument("--plain", action="store_true", help="offline: the plain Seol solve even on a profile with a "
                   "noise estimate (default there: the noise-robust solve, docs/robustness.md)")
    g.add_argument("--trend", type=float, help="noise-robust offline solve: l1 trend filter penalty on the weight "
                   f"curves, in weight-noise sds per shape (default {RobustSettings.trend:g}; 0 turns it off; "
                   "docs/robustness.md)")
    g.add_argument("--marker-weight", action="append", metavar="LABEL=W", default=[],
                   help="per-marker weight of the position term (glob patterns allowed; repeatable)")
    if stream:
        g.add_argument("--stream", action="store_true", help="run the take through the paper's sliding-window "
                       "streaming solver (Seol et al. 2012) instead of the offline solve (the live pipeline's "
                       "movement on a tuned profile is the filtered per-frame step: docs/modes.md)")
        g.add_argument("--window", type=int, help=f"with --stream: window K in frames (default {D.window})")
        g.add_argument("--lookahead", type=int,
                       help=f"with --stream: lookahead L < K in frames (default {D.lookahead})")


def movement_options(args: argparse.Namespace) -> dict:
    """Options for the movement factory (livecap.modes.movement); unset flags keep MovementSettings' defaults."""
    opts = {k: getattr(args, k, None) for k in ("alpha", "beta", "prior_threshold", "start", "end", "missing",
                                                "limits", "window", "lookahead", "trend")}
    if getattr(args, "stream", False):
        opts["stream"] = True
    if getattr(args, "plain", False):
        opts["robust"] = False
    prior = getattr(args, "prior", None)
    if prior is not None and prior not in ("shapes", "none", "profile") and not prior.endswith(".npz"):
        names, weights, _ = read_weights_csv(prior)
        prior = {"names": names, "weights": weights}
    opts["prior"] = prior
    mw = {}
    for item in getattr(args, "marker_weight", None) or []:
        label, sep, value = item.rpartition("=")
        if not sep or not label:
            raise ValueError(f"--marker-weight {item!r}: expected LABEL=WEIGHT")
        mw[label] = float(value)
    opts["marker_weights"] = mw or None
    return {k: v for k, v in opts.items() if v is not None}
