"""Movement-matching solvers built from a Profile and plain options (used by modes.py and the CLI).

Defaults (alpha 1, beta 0.1, prior from the rig's shapes plus the neutral; the rig's limits by
clipping: offline the solved take, streaming the published frame) were chosen on the demo take
and a synthetic take (docs/movement.md lists the measurements); every one is an option.

Offline on a profile that carries a noise estimate (``settings["robust"]``, stored by
``livecap.modes.robust.tune_profile`` on every CLI calibration path) the mode is the noise-robust
:class:`livecap.modes.robust_movement.RobustMovement` (smoothed markers, alpha 0, beta from the
smoother, L1 at the noise threshold, bounded limits, smoothed weights); explicit options still
override its alpha/beta/limits/...; option ``robust: false`` gives the plain Seol solve.
"""

from __future__ import annotations

import fnmatch
import logging
from collections.abc import Mapping

import numpy as np

from livecap.calibration.profile import Profile
from livecap.modes.robust import robust_settings
from livecap.modes.robust_movement import BOUND_TOL, RobustMovement, smoother_beta
from solvers.blocks import IllPosedError
from solvers.movement import MovementMatching
from solvers.prior import PCAPrior
from solvers.streaming import StreamingMovement

log = logging.getLogger(__name__)

DEFAULTS = {"alpha": 1.0, "beta": 0.1, "prior": "shapes", "prior_threshold": 1e-6, "ridge": 0.0,
            "start": "neutral", "end": "neutral", "missing": "fill", "window": 24, "lookahead": 0}


def marker_weights(labels: list[str], spec: Mapping[str, float] | None) -> np.ndarray | None:
    """Per-marker weights of the position term from {label or glob pattern: weight} (others 1)."""
    if not spec:
        return None
    w = np.ones(len(labels))
    for pattern, value in spec.items():
        hit = [i for i, lab in enumerate(labels) if fnmatch.fnmatchcase(lab, pattern)]
        if not hit:
            raise ValueError(f"marker weight {pattern!r} matches no marker label")
        w[hit] = float(value)
    return w


def build_prior(profile: Profile, spec, threshold: float) -> PCAPrior | None:
    """``"shapes"`` (the rig's shapes + neutral as frames), ``"none"``, or a T x m weight animation."""
    if spec is None or (isinstance(spec, str) and spec == "none"):
        return None
    if isinstance(spec, str):
        if spec != "shapes":
            raise ValueError(f"unknown prior {spec!r}: use 'shapes', 'none' or a weights CSV")
        return PCAPrior.from_shapes(profile.basis, threshold)
    if isinstance(spec, Mapping):  # {"names": [...], "weights": T x k}: matched to the rig by shape name
        names, W = list(spec["names"]), np.asarray(spec["weights"], dtype=np.float64)
        unknown = sorted(set(names) - set(profile.names))
        if unknown:
            raise ValueError(f"prior animation has shapes the rig lacks: {unknown[:5]}")
        full = np.zeros((len(W), len(profile.names)))
        for j, name in enumerate(names):
            full[:, profile.names.index(name)] = W[:, j]
        return PCAPrior.from_animation(profile.basis, full, threshold)
    return PCAPrior.from_animation(profile.basis, np.asarray(spec, dtype=np.float64), threshold)


def build_movement(profile: Profile, options: Mapping | None = None):
    """Offline :class:`MovementMatching` (with ``step`` for live use), or with ``stream`` the
    :class:`StreamingMovement` sliding-window solver.

    When the system is singular (more shapes than the markers and prior can pin down, as on
    film-scale rigs) and no ridge was asked for, a ridge of 1e-6 of the basis's mean column
    energy makes it well posed instead of failing.
    """
    given = {k: v for k, v in (options or {}).items() if v is not None}
    noise = profile.settings.get("robust", {}).get("noise_mm")
    robust = noise is not None and not given.get("stream") and bool(given.get("robust", True))
    settings = robust_settings(profile, given)  # the robust defaults, the tuned profile, then the options
    lag = int(settings["lag"])
    base = {**DEFAULTS, "alpha": 0.0, "beta": smoother_beta(lag), "limits": "bound",
            "bound_options": {"tol": BOUND_TOL}} if robust else DEFAULTS
    o = {**base, **given}
    try:
        inner = _build(profile, o)
    except IllPosedError:
        if float(o["ridge"]) > 0:
            raise
        ridge = 1e-6 * float(np.mean(np.sum(profile.basis**2, axis=0)))
        log.info("movement system singular; adding ridge %.3g", ridge)
        inner = _build(profile, {**o, "ridge": ridge})
    if not robust:
        return inner
    return RobustMovement(inner, float(noise), lag=lag, trend=float(settings["trend"]),
                          reweight=int(given.get("reweight", 0)))


def _build(profile: Profile, o: dict):
    alpha = float(o["alpha"])
    prior = build_prior(profile, o["prior"], float(o["prior_threshold"])) if alpha > 0 else None
    if prior is None:
        alpha = 0.0
    common = dict(alpha=alpha, prior=prior, beta=float(o["beta"]), ridge=float(o["ridge"]),
                  marker_weights=marker_weights(profile.labels, o.get("marker_weights")))
    if o.get("stream"):
        return StreamingMovement(profile.basis, profile.lower, profile.upper, window=int(o["window"]),
                                 lookahead=int(o["lookahead"]),
                                 limits="clip" if o.get("limits") in (None, "bound") else o["limits"], **common)
    return MovementMatching(profile.basis, profile.lower, profile.upper, start=o["start"], end=o["end"],
                            missing=o["missing"], limits=o.get("limits") or "clip", window=int(o["window"]),
                            lookahead=int(o["lookahead"]), bound_options=o.get("bound_options"), **common)
