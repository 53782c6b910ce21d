"""Movement-matching solvers built from a Profile and plain options (used by the registry and the CLI).

Every tunable is a field of :class:`MovementSettings`, resolved by :func:`movement_settings`.
Defaults (alpha 1, beta 0.1, prior from the rig's shapes plus the neutral; the rig's limits by clipping:
offline the solved take, streaming the published frame) were chosen on the demo take
and a synthetic take (docs/movement.md lists the measurements); every one is an option.

Offline on a profile that carries a noise estimate (``settings["robust"]``, stored by
``livecap.modes.robust.tune_profile`` on every CLI calibration path) the mode is the noise-robust
:class:`livecap.modes.robust_movement.RobustMovement` (smoothed markers, alpha 0, beta from the
smoother, L1 at the noise threshold, bounded limits, smoothed weights); explicit options still
override its alpha/beta/limits/...; option ``robust: false`` gives the plain Seol solve. An animation prior
(the profile's, stored by ``calibrate --prior``, by default; or ``prior``) replaces its L1 term there, weighted
by :func:`prior_alpha` (issue 41.3: it was silently weighted 0). Streamed (``step``, ``livecap run``) the same
profile gives :class:`livecap.modes.robust_movement.StreamedMovement` (the ``kalman`` mode's marker filter, one
movement step a frame, the robust modes' IMM; the ``live_*`` settings); ``stream: true`` / ``movement-stream`` is
Seol's sliding window with prefactored matrices.
"""

from __future__ import annotations

import fnmatch
import logging
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from functools import partial
from typing import Any

import numpy as np

from livecap.calibration.animation_prior import AnimationPrior, prior_from_spec
from livecap.calibration.profile import Profile
from livecap.modes.quiet import marker_noise, mismatched
from livecap.modes.robust import robust_settings, sparse_fit, warn_untuned, weight_filter
from livecap.modes.robust_movement import BOUND_TOL, RobustMovement, StreamedMovement, smoother_beta
from solvers.blocks import IllPosedError
from solvers.filters import savgol_weights
from solvers.marker_kalman import StreamingMarkerKalman
from solvers.movement import MovementMatching
from solvers.prior import PCAPrior
from solvers.streaming import StreamingMovement

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MovementSettings:
    """Every tunable of the movement modes (Seol et al. 2012), with its default. Build with
    :func:`movement_settings`; on a profile with a noise estimate the offline defaults change to
    the noise-robust solve's (alpha 0, beta from the smoother, bounded limits)."""

    alpha: float = 1.0  # PCA prior weight (§5; 0 disables it)
    beta: float = 0.1  # position (Sobolev) term weight (§7.1)
    prior: Any = "shapes"  # "shapes" (rig shapes + neutral), "none", a T x m animation or {"names", "weights"}
    prior_threshold: float = 1e-6  # PCA eigenvalues below this fraction of the largest are dropped
    ridge: float = 0.0  # Tikhonov term on the weights (0: none; a tiny one is added if the system is singular)
    start: str = "neutral"  # boundary at the first frame: neutral, free or fit
    end: str = "neutral"  # boundary at the last frame
    missing: str = "fill"  # offline missing markers: fill from the rig's fit, or drop their rows exactly
    window: int = 24  # sliding window K, frames (``stream`` and the plain solve's ``step``)
    lookahead: int = 0  # sliding window lookahead L < K, frames (likewise)
    limits: str | None = None  # none, clip or bound (None: clip; streaming clips the published frame)
    bound_options: Mapping | None = None  # ADMM settings of limits="bound"
    marker_weights: Mapping[str, float] | None = None  # {label or glob: weight} of the position term
    stream: bool = False  # the sliding-window streaming solver instead of the offline solve
    robust: bool = False  # offline noise-robust solve (resolved: the profile has a noise estimate, not --plain)
    noise_mm: float | None = None  # the profile's marker noise estimate, mm (None: never tuned)
    lag: int = 4  # noise-robust solve: marker smoother half-width, frames (RobustSettings.lag)
    trend: float = 10.0  # noise-robust solve: weight trend filter penalty, weight-noise sds (0: none)
    reweight: int = 0  # noise-robust solve: reweighted-L1 re-solves (Candes et al. 2008)
    # noise-robust solve streamed (``step``, livecap.modes.robust_movement.StreamedMovement; issues 35 / 41, chosen on
    # the ICT takes of S07-001 and apfel and the AnimFace takes, docs/robustness.md "Streamed movement"):
    live_beta: float = 5.0  # position (Sobolev) weight against the movement term 1, on white noise (streamed_beta)
    live_gain: float = 0.3  # marker noise variance left by the marker filter (the L1 threshold's noise)
    live_weight_gain: float = 3.0  # IMM measurement variance per shape, in sigma^2 / |b_k|^2


_FIELDS = frozenset(f.name for f in fields(MovementSettings))


def movement_settings(profile: Profile, options: Mapping | None = None) -> MovementSettings:
    """The one place the movement modes' settings are resolved: defaults (plain, or noise-robust on a
    profile with a noise estimate unless ``robust: false`` or ``stream``), then ``options`` (None ignored)."""
    given = {k: v for k, v in (options or {}).items() if v is not None}
    noise = profile.settings.get("robust", {}).get("noise_mm")
    robust = noise is not None and not given.get("stream") and bool(given.get("robust", True))
    rs = robust_settings(profile, given)  # lag and trend: the robust defaults, the tuned profile, then options
    base = MovementSettings(noise_mm=None if noise is None else float(noise), lag=int(rs.lag),
                            trend=float(rs.trend), robust=robust)
    if robust:
        base = replace(base, alpha=0.0, beta=smoother_beta(base.lag), limits="bound",
                       bound_options={"tol": BOUND_TOL})
        if profile.prior is not None and "prior" not in given:  # the one ``calibrate --prior`` stored (issue 41.3)
            base = replace(base, prior="profile")
        if _animation_prior(given.get("prior", base.prior)):
            base = replace(base, alpha=prior_alpha(float(noise), base.lag))
        base = replace(base, marker_weights=misfit_weights(profile))
    resolved = ("robust", "noise_mm", "lag", "trend")  # from the profile and robust_settings above
    return replace(base, **{k: v for k, v in given.items() if k in _FIELDS and k not in resolved})


def _animation_prior(spec) -> bool:
    """True when ``spec`` names a prior learned from animation (the user asked for it: it must be used)."""
    return spec is not None and not (isinstance(spec, str) and spec in ("shapes", "none"))


def prior_alpha(noise_mm: float, lag: int) -> float:
    """The noise-robust solve's prior weight: the Gaussian prior's Mahalanobis cost (Seol §5, Eq. 4) against the
    velocity term normalised to 1, by the same inverse-variance weighting that sets beta (module docstring of
    livecap.modes.robust_movement): the velocity residual's variance after the smoother, sigma^2 sum(diff(h)^2)."""
    h = savgol_weights(int(lag))
    return float(noise_mm**2 * np.sum(np.diff(np.r_[0.0, h, 0.0]) ** 2))


def misfit_weights(profile: Profile) -> dict[str, float] | None:
    """Under measured model mismatch (``livecap.modes.quiet.mismatched``), each marker's position-term weight
    ``min(1, (sigma / sigma_i)^2)`` with sigma_i calibration's per-marker residual (issue 35.2): a marker the rig
    cannot follow (the actor's mouth corners and chin) counts less, so its misfit is left as residual instead of
    being explained by a frown; no marker counts more than the overall noise says. None otherwise (same-rig takes
    with white noise). The value is M's diagonal, which ``solvers.blocks.MovementBlocks`` squares: a squared residual
    counts ``(sigma / sigma_i)^4``, the square of its inverse variance. The inverse variance itself (M = sigma /
    sigma_i) was measured and not kept: smile r +0.03 on the cheek take, but mouthFrown up on the jaw take and the
    model-mismatch takes (docs/robustness.md "Movement's right smile on the cheek take")."""
    per = marker_noise(profile)
    if per is None or not mismatched(profile):
        return None
    sigma = float(profile.settings["robust"]["noise_mm"])
    return {lab: float(min(1.0, (sigma / max(v, 1e-9)) ** 2)) for lab, v in zip(profile.labels, per, strict=True)}


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
    """``"shapes"`` (the rig's shapes + neutral as frames), ``"none"``, ``"profile"`` (the animation prior
    ``calibrate --prior`` stored), an animation prior (``livecap prior build``'s .npz), or a T x m weight
    animation."""
    if spec is None or (isinstance(spec, str) and spec == "none"):
        return None
    spec = prior_from_spec(spec, profile.prior)
    if isinstance(spec, AnimationPrior):
        spec.check(profile.names)
        return PCAPrior.from_moments(profile.basis, spec.mean, spec.cov, threshold)
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


def build_movement(profile: Profile, options: Mapping | MovementSettings | None = None):
    """Offline :class:`MovementMatching` (with ``step`` for live use), or with ``stream`` the
    :class:`StreamingMovement` sliding-window solver.

    When the system is singular (more shapes than the markers and prior can pin down, as on
    film-scale rigs) and no ridge was asked for, a ridge of 1e-6 of the basis's mean column
    energy makes it well posed instead of failing.
    """
    s = options if isinstance(options, MovementSettings) else movement_settings(profile, options)
    plain_asked = isinstance(options, Mapping) and options.get("robust") is False
    if not s.stream and s.noise_mm is None and not plain_asked:
        warn_untuned(profile, "movement", "it runs the plain Seol solve, not the noise-robust one")
    try:
        inner = _build(profile, s)
    except IllPosedError:
        if float(s.ridge) > 0:
            raise
        ridge = 1e-6 * float(np.mean(np.sum(profile.basis**2, axis=0)))
        log.info("movement system singular; adding ridge %.3g", ridge)
        inner = _build(profile, replace(s, ridge=ridge))
    if not s.robust:
        return inner
    # with a prior from animation, that prior is the plausibility term; the L1 (a sparse prior) would count twice
    return RobustMovement(inner, float(s.noise_mm), lag=s.lag, trend=s.trend, reweight=int(s.reweight),
                          l1=inner.blocks.alpha == 0, live=partial(_live, profile, s))


def _live(profile: Profile, s: MovementSettings) -> StreamedMovement:
    """The streamed form of the noise-robust solve (issues 35 / 41): the ``kalman`` mode's marker filter (its default
    settings, one frame of latency), a movement step a frame with the sparse fit's L1 at the filtered noise, the
    robust modes' IMM."""
    rs = robust_settings(profile, {})
    markers = StreamingMarkerKalman(profile.n_markers, lag=1)
    fit = sparse_fit(profile, rs, float(s.live_gain))
    return StreamedMovement(profile.basis, markers, fit, streamed_beta(profile, s),
                            weight_filter(profile, rs, float(s.live_weight_gain)))


def streamed_beta(profile: Profile, s: MovementSettings) -> float:
    """The streamed step's position weight: ``live_beta`` scaled by the share of calibration's noise variance that is
    frame-to-frame jitter, never below the offline solve's ``beta``. Under model mismatch the position residual is
    mostly what the rig cannot explain (issue 35.2), which changes little from frame to frame, so by inverse-variance
    weighting the position term counts less and the movement term matches the markers' motion."""
    tuned = profile.settings.get("robust", {})
    noise, jitter = tuned.get("noise_mm"), tuned.get("jitter_mm")
    share = 1.0 if not noise or jitter is None else min(1.0, (float(jitter) / float(noise)) ** 2)
    return max(float(s.beta), float(s.live_beta) * share)


def _build(profile: Profile, s: MovementSettings):
    alpha = float(s.alpha)
    prior = build_prior(profile, s.prior, float(s.prior_threshold)) if alpha > 0 else None
    if prior is None:
        alpha = 0.0
    common = dict(alpha=alpha, prior=prior, beta=float(s.beta), ridge=float(s.ridge),
                  marker_weights=marker_weights(profile.labels, s.marker_weights))
    if s.stream:
        return StreamingMovement(profile.basis, profile.lower, profile.upper, window=int(s.window),
                                 lookahead=int(s.lookahead),
                                 limits="clip" if s.limits in (None, "bound") else s.limits, **common)
    return MovementMatching(profile.basis, profile.lower, profile.upper, start=s.start, end=s.end,
                            missing=s.missing, limits=s.limits or "clip", window=int(s.window),
                            lookahead=int(s.lookahead), bound_options=s.bound_options, **common)
