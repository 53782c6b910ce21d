"""Noise-robust solving: regularisation selected from data, noise-floor rest pull, filters.

This module wires ``solvers.sparse_fit``, ``solvers.regularisation``, ``solvers.observability``
and ``solvers.filters`` to Profiles and modes:

* ``RobustSettings``: every knob of these modes in one frozen dataclass with its default;
  ``robust_settings(profile, options)`` is the one place it is resolved (defaults, what tuning
  stored in the profile, then options);

* ``tune_profile(profile, targets, valid, rate)`` estimates the marker noise, selects the ridge
  of the plain prior fit by held-out-marker cross-validation (GCV alongside) and the ridge of the
  sparse fit the same way, and stores it all in ``profile.settings["robust"]``, so a saved
  profile starts a session with the selected values;
* ``robust_solver`` is the ``robust`` streaming mode, three stages each set from the noise:
  a causal quadratic end-point filter on the markers (no lag on motion up to constant
  acceleration), a sparse bounded fit (L1 at the universal threshold of the filtered noise, with
  hysteresis; small ridge from held-out markers), and on the weights an IMM of a 'hold' and a
  'move' constant-velocity Kalman filter (``solvers.tracking``; no lag on ramps) whose
  measurement variance per shape is the fit's noise ``sigma^2 gain / |b_k|^2`` (option
  ``weight_filter: "1e"`` gives the earlier 1€ stage);
* ``smooth_solver`` is ``robust-lag``: the same sparse fit on markers smoothed by a centred
  quadratic over ``2 lag + 1`` frames, streamed with ``lag`` frames of latency; offline (zero
  phase) the weight curves are then l1-trend-filtered (``trend``);
* ``filtered(factory)`` wraps any registered mode's factory with the 1€ weight filter, so modes
  that arrive later (QP, movement, RBF) get a filtered variant for free.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields, replace

import numpy as np

from livecap.calibration.profile import Profile
from solvers.filters import CausalPolyFilter, FilteredSolver, FixedLagSmoother, OneEuroFilter, savgol_weights
from solvers.observability import noise_floor
from solvers.regularisation import PriorLeastSquares, estimate_noise, fit_residual, gcv_ridge, holdout_ridge
from solvers.sparse_fit import HysteresisSparseFit, holdout_sparse_ridge, l1_weights, universal_threshold
from solvers.tracking import IMMFilter, dwna_variance
from solvers.trend import TrendFilter

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RobustSettings:
    """Every tunable of the robust modes, with the defaults used when a profile was never tuned
    (docs/robustness.md has the measurements behind them). Build with :func:`robust_settings`."""

    noise_mm: float = 0.5  # marker noise sigma per coordinate, mm (tuned: estimated from a take)
    prior_sd: float = 0.3  # untuned prior-fit ridge: the MAP ridge (noise / prior_sd)^2 of N(0, prior_sd^2) weights
    ridge: float | None = None  # prior fit's ridge (tuned: held-out markers; None: the MAP ridge above)
    rest_pull: float = 1.0  # prior fit: shapes stay at rest until their evidence exceeds this many noise-floor sds
    sparse_ridge: float = 1.0  # sparse fit's ridge (tuned: held-out markers; option ``ridge`` overrides)
    z_enter: float = 0.0  # sparse fit: a resting shape enters above this many noise sds (0: sqrt(2 ln m))
    z_stay: float = 2.0  # ... and an active one stays active above this many
    marker_window: float = 0.1  # causal quadratic marker filter span, seconds (12 frames at 120 Hz)
    min_cutoff: float = 1.0  # 1€ filter on weights, Hz
    euro_beta: float = 30.0  # 1€ speed coefficient, per (weight unit / s) (key ``beta`` in profiles before 2026-12)
    d_cutoff: float = 1.0  # 1€ derivative cutoff, Hz
    lag: int = 4  # fixed-lag smoother latency, frames
    trend: float = 10.0  # offline l1 trend filter on the weight curves, in weight-noise sds per shape (0: none)
    weight_filter: str = "imm"  # robust mode's weight stage: "imm" (hold/move Kalman) or "1e" (One Euro)
    hold_accel: float = 0.5  # IMM 'hold' model: acceleration sd, weight units / s^2
    move_accel: float = 80.0  # IMM 'move' model: acceleration sd, weight units / s^2
    sojourn: float = 0.8  # IMM mean time in a mode, seconds (Markov switching probability 1 / (sojourn rate))
    weight_noise: str = "fit"  # IMM measurement variance per shape: "fit" or "marginal" (see weight_noise)
    rate: float = 120.0  # frame rate, Hz (tuned: the tuning take's)

    @property
    def prior_ridge(self) -> float:
        """The prior fit's ridge: the tuned/given one, else the MAP ridge of the untuned prior."""
        return (self.noise_mm / self.prior_sd) ** 2 if self.ridge is None else float(self.ridge)


KNOBS = frozenset(f.name for f in fields(RobustSettings))


def robust_settings(profile: Profile, options: Mapping | RobustSettings | None = None) -> RobustSettings:
    """The one place the robust modes' settings are resolved: defaults, then what tuning stored in
    ``profile.settings["robust"]``, then ``options`` (unset ones, None, ignored). Option ``ridge``
    sets both fits' ridges, as ``--ridge`` always did."""
    if isinstance(options, RobustSettings):
        return options
    stored = dict(profile.settings.get("robust", {}))
    if "beta" in stored:  # the 1€ speed coefficient's old key (it clashed with movement's beta)
        stored.setdefault("euro_beta", stored.pop("beta"))
    given = {k: v for k, v in (options or {}).items() if v is not None and k in KNOBS}
    s = replace(RobustSettings(), **{**{k: v for k, v in stored.items() if k in KNOBS}, **given})
    if "ridge" in given:
        s = replace(s, sparse_ridge=float(given["ridge"]))
    return s


def untuned(profile: Profile) -> bool:
    """True when calibration stored no noise estimate (profiles written before every path tuned)."""
    return profile.settings.get("robust", {}).get("noise_mm") is None


def warn_untuned(profile: Profile, mode: str, fallback: str) -> None:
    """One warning per solver build: the mode falls back because the profile carries no noise estimate."""
    if untuned(profile):
        log.warning("mode %s: the profile has no noise estimate, so %s; re-run 'livecap calibrate' "
                    "(it stores one) or give the take to tune on with --tune", mode, fallback)


NOISE_DISAGREES = 3.0  # residual / jitter above this: the data were smoothed, or the rig does not fit the actor


def tune_profile(profile: Profile, targets: np.ndarray, valid: np.ndarray, rate: float,
                 noise_mm: float | None = None) -> dict:
    """Select the noise level and the ridges from a take's stabilised displacements; store in the profile.

    The noise is what the solvers must not explain (issue 35.2): per marker the larger of the frame-to-frame
    jitter (second differences) and the rig's fit residual (``solvers.regularisation.fit_residual``, which reads
    the jitter on white noise and more where the rig cannot follow the actor), then the RMS over markers. A
    smoothed capture cannot drive it to zero that way; ``noise_mm`` (``--noise-mm``) replaces it. A warning says
    when the two estimates disagree. Deterministic: the folds, frame thinning and grids are fixed. Returns the
    stored dict.
    """
    jitter = estimate_noise(targets, valid)
    held = holdout_ridge(profile.basis, targets, valid, lower=profile.lower, upper=profile.upper)
    per_marker = np.maximum(jitter, fit_residual(profile.basis, targets, valid, held.value))
    residual = float(np.sqrt(np.mean(per_marker**2)))
    noise = float(noise_mm) if noise_mm is not None else residual
    if noise_mm is None and residual > NOISE_DISAGREES * jitter:
        worst = np.argsort(per_marker)[::-1][:3]
        log.warning("marker noise: frame-to-frame jitter %.3f mm but the rig leaves %.3f mm RMS unexplained "
                    "(most at %s): the data look smoothed or the rig does not fit this actor; solving with "
                    "%.3f mm (override with --noise-mm)", jitter, residual,
                    ", ".join(f"{profile.labels[i]} {per_marker[i]:.2f}" for i in worst), noise)
    gcv = gcv_ridge(profile.basis, targets, valid)
    tuned = {"noise_mm": noise, "jitter_mm": jitter, "residual_mm": residual,
             "marker_noise_mm": [float(x) for x in per_marker],
             "noise_source": "given" if noise_mm is not None else "residual" if residual > jitter else "jitter",
             "ridge": held.value, "ridge_gcv": gcv.value, "rate": float(rate), "criterion": held.criterion}
    # the sparse fit sees markers through the causal filter: select its ridge on what it will see
    filt = marker_filter(float(rate), RobustSettings.marker_window)
    smoothed = filt.filter(targets, np.broadcast_to(np.asarray(valid, bool)[..., None], np.shape(targets)))
    z = universal_threshold(profile.basis.shape[1])
    sparse = holdout_sparse_ridge(profile.basis, smoothed, valid, noise * np.sqrt(filt.noise_gain), z,
                                  profile.lower, profile.upper)
    tuned.update(sparse_ridge=sparse.value, sparse_criterion=sparse.criterion)
    profile.settings["robust"] = tuned
    tuned.update(acting_density(profile, targets, valid))
    profile.settings.setdefault("noise_mm", noise)
    profile.settings.setdefault("ridge_selected", held.value)
    return tuned


ACTIVE_WEIGHT = 0.05  # a shape counts as active in a frame above this weight
SPARSE_ACTING = 0.08  # mean share of shapes active in the sparse fit below which the acting is sparse
ACTING_EVIDENCE = 0.2  # share of frames with any active shape below which the take says nothing (a still face)


def acting_density(profile: Profile, targets: np.ndarray, valid: np.ndarray) -> dict:
    """What the tuning take says of the acting, for the default mode (livecap.modes.registry.resolve_mode): the
    sparse fit (``robust``, run over the take) keeps few shapes where the acting is sparse and many where it is dense.

    Measured (issue 41.1, 2026-12-04, docs/modes.md): the bundled demo take's scripted acting keeps 2.3 of 43
    shapes a frame on average (0.05); takes driven by the six real performances keep 6-13 of 53 on the ICT rig and
    6-12 of 43 on the demo rig (0.11-0.27), though 19-32 are truly active. A still take (a neutral) keeps none:
    no evidence, ``acting`` None."""
    from livecap.modes.robust_take import whole_take

    W = whole_take(robust_solver(profile), targets, valid)
    active = np.sum(W > ACTIVE_WEIGHT, axis=1)
    if not len(W) or np.mean(active > 0) < ACTING_EVIDENCE:
        return {"acting": None, "active_fraction": None}
    share = float(np.mean(active) / W.shape[1])
    return {"acting": "sparse" if share < SPARSE_ACTING else "dense", "active_fraction": share}


def override_noise(profile: Profile, noise_mm: float) -> None:
    """``--noise-mm`` on a saved profile: every mode that reads the noise uses ``noise_mm`` instead."""
    if not noise_mm > 0:
        raise ValueError(f"--noise-mm must be positive, got {noise_mm}")
    profile.settings["robust"] = {**profile.settings.get("robust", {}), "noise_mm": float(noise_mm),
                                  "noise_source": "given"}
    profile.settings["noise_mm"] = float(noise_mm)


def marker_filter(rate: float, seconds: float) -> CausalPolyFilter:
    """The causal quadratic end-point filter spanning ``seconds`` (at least 4 frames)."""
    return CausalPolyFilter(max(4, int(round(seconds * rate))), order=2)


def sparse_fit(profile: Profile, options: Mapping | RobustSettings | None, gain: float) -> HysteresisSparseFit:
    """The sparse fit for markers whose noise variance was scaled by ``gain`` by a filter."""
    s = robust_settings(profile, options)
    B = profile.basis
    sigma = float(s.noise_mm) * np.sqrt(gain)
    z_enter = float(s.z_enter) or universal_threshold(B.shape[1])
    z_stay = min(float(s.z_stay), z_enter)
    return HysteresisSparseFit(B, profile.lower, profile.upper, float(s.sparse_ridge),
                               enter=l1_weights(B, sigma, z_enter), stay=l1_weights(B, sigma, z_stay))


def prior_solver(profile: Profile, options: Mapping | RobustSettings | None = None) -> PriorLeastSquares:
    """The per-frame fit: selected ridge and a noise-floor rest-pull."""
    s = robust_settings(profile, options)
    B = profile.basis
    ridge = s.prior_ridge
    H = B.T @ B + ridge * np.eye(B.shape[1])
    pull = 2.0 * float(s.rest_pull) * noise_floor(B, float(s.noise_mm), ridge) * np.diag(H)
    return PriorLeastSquares(B, profile.lower, profile.upper, ridge, rest_pull=pull)


def one_euro(profile: Profile, options: Mapping | RobustSettings | None = None) -> OneEuroFilter:
    s = robust_settings(profile, options)
    return OneEuroFilter(float(s.rate), s.min_cutoff, s.euro_beta, s.d_cutoff)


def weight_noise(profile: Profile, options: Mapping | RobustSettings | None, gain: float) -> np.ndarray:
    """Per-shape variance of a fitted weight under the (filtered) marker noise.

    ``weight_noise: "fit"`` (default): ``sigma^2 gain / |b_k|^2``, the noise of ``b_k^T s / |b_k|^2``,
    i.e. of a shape fitted alone (the sparse fit's active sets are small; its L1 threshold uses
    the same scale). ``"marginal"``: ``sigma^2 gain [(B^T B + ridge I)^-1]_kk``, the marginal variance
    of the full least-squares fit, larger for shapes that other shapes can mimic (smooths them more).
    """
    s = robust_settings(profile, options)
    sigma, B = float(s.noise_mm), profile.basis
    kind = str(s.weight_noise).lower()
    if kind == "marginal":
        ridge = float(s.sparse_ridge)
        return sigma**2 * float(gain) * np.diag(np.linalg.inv(B.T @ B + max(ridge, 1e-9) * np.eye(B.shape[1])))
    if kind != "fit":
        raise ValueError(f"unknown weight noise model {kind!r} (choose fit or marginal)")
    norms = np.maximum(np.linalg.norm(B, axis=0), 1e-9)
    return sigma**2 * float(gain) / norms**2


def imm_filter(profile: Profile, options: Mapping | RobustSettings | None, gain: float) -> IMMFilter:
    """The IMM weight stage: 'hold' and 'move' constant-velocity models (acceleration sd in weight units
    per s^2, converted to per-frame DWNA variances at the stream's rate), R per shape from the noise."""
    s = robust_settings(profile, options)
    rate = float(s.rate)
    return IMMFilter(dwna_variance(float(s.hold_accel), rate), dwna_variance(float(s.move_accel), rate),
                     weight_noise(profile, s, gain), sojourn_frames=max(2.0, float(s.sojourn) * rate))


def weight_filter(profile: Profile, options: Mapping | RobustSettings | None = None,
                  gain: float = 1.0) -> IMMFilter | OneEuroFilter:
    """The robust mode's weight stage, per the ``weight_filter`` setting ("imm" or "1e")."""
    s = robust_settings(profile, options)
    kind = str(s.weight_filter).lower()
    if kind in ("1e", "one-euro", "oneeuro"):
        return one_euro(profile, s)
    if kind != "imm":
        raise ValueError(f"unknown weight filter {kind!r} (choose imm or 1e)")
    return imm_filter(profile, s, gain)


def robust_solver(profile: Profile, options: Mapping | RobustSettings | None = None) -> FilteredSolver:
    """Streaming: causal quadratic marker filter -> sparse fit -> IMM (or 1€) on the weights (no fixed latency)."""
    s = robust_settings(profile, options)
    if not isinstance(options, RobustSettings):
        warn_untuned(profile, "robust", f"it assumes {s.noise_mm:g} mm marker noise")
    markers = marker_filter(float(s.rate), float(s.marker_window))
    return FilteredSolver(sparse_fit(profile, s, markers.noise_gain), marker_filter=markers,
                          weight_filter=weight_filter(profile, s, markers.noise_gain))


def smooth_solver(profile: Profile, options: Mapping | RobustSettings | None = None) -> LookaheadSolver:
    """Lookahead / offline: centred quadratic marker smoothing over 2 lag + 1 frames -> sparse fit;
    ``latency_frames`` = lag when streamed, none offline."""
    s = robust_settings(profile, options)
    if not isinstance(options, RobustSettings):
        warn_untuned(profile, "robust-lag", f"it assumes {s.noise_mm:g} mm marker noise")
    lag, trend = int(s.lag), float(s.trend)
    gain = float(np.sum(savgol_weights(lag) ** 2))
    offline = TrendFilter.for_basis(profile.basis, float(s.noise_mm) * np.sqrt(gain), trend) if trend > 0 else None
    return LookaheadSolver(sparse_fit(profile, s, gain), FixedLagSmoother(lag), offline)


class LookaheadSolver:
    """``step``: streamed with ``lag`` frames of lookahead (markers smoothed around frame t - lag,
    whose weights it returns); ``solve``: the whole take, the smoother centred on every frame, then
    the weight curves filtered by ``offline`` (zero phase: the l1 trend filter keeps blink peaks)."""

    def __init__(self, inner, smoother: FixedLagSmoother, offline: TrendFilter | None = None) -> None:
        self.inner, self.smoother, self.offline = inner, smoother, offline
        self.lower, self.upper = inner.lower, inner.upper
        self._valid: deque = deque(maxlen=smoother.lag + 1)

    @property
    def latency_frames(self) -> int:
        return self.smoother.lag

    def reset(self) -> None:
        self.inner.reset()
        self.smoother.reset()
        self._valid.clear()

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        valid = np.asarray(valid, dtype=bool)
        if not self._valid:  # the smoother pads its past with the first frame; so does the mask
            self._valid.extend([valid] * self.smoother.lag)
        self._valid.append(valid)
        smoothed = self.smoother.step(target, np.broadcast_to(valid[:, None], np.shape(target)))
        return self.inner.step(smoothed, self._valid[0])

    def solve(self, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
        self.inner.reset()
        smoothed = self.smoother.filter(targets, np.broadcast_to(np.asarray(valid, bool)[..., None], targets.shape))
        W = np.array([self.inner.step(smoothed[t], valid[t]) for t in range(len(targets))])
        return W if self.offline is None else np.clip(self.offline.filter(W), self.lower, self.upper)


def filtered(factory: Callable) -> Callable:
    """Any mode's factory, with the 1€ filter on its weights (offline ``solve`` is filtered too)."""

    def build(profile: Profile, options: dict | None = None):
        inner = factory(profile, options or {})
        filt = one_euro(profile, options)
        if hasattr(inner, "solve"):
            return _OfflineFiltered(inner, weight_filter=filt, lower=profile.lower, upper=profile.upper)
        return FilteredSolver(inner, weight_filter=filt, lower=profile.lower, upper=profile.upper)

    return build


class _OfflineFiltered(FilteredSolver):
    def solve(self, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
        W = self.inner.solve(targets, valid)
        return np.clip(self.weight_filter.filter(W), self.lower, self.upper)


ROBUST_MODES: dict[str, Callable] = {"robust": robust_solver, "robust-lag": smooth_solver}
