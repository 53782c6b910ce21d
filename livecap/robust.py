"""Noise-robust solving: regularisation selected from data, observability-aware priors, filters.

This module wires ``solvers.regularisation``, ``solvers.observability`` and ``solvers.filters``
to Profiles and modes:

* ``tune_profile(profile, targets, valid, rate)`` estimates the marker noise, selects the ridge
  by held-out-marker cross-validation (GCV alongside) and stores it all in
  ``profile.settings["robust"]`` (plus ``settings["ridge"]``, ``settings["noise_mm"]``), so a
  saved profile starts a session with the selected values;
* ``robust_solver`` is the ``robust`` streaming mode: a bounded prior least-squares fit per frame
  (selected ridge, a rest-pull at each shape's noise floor, optional tying of indistinguishable
  pairs) followed by a 1€ filter on the weights;
* ``smooth_solver`` is ``robust-lag``: the same fit with a fixed-lag smoother (latency stated in
  frames) for offline solves and lookahead streams;
* ``filtered(factory)`` wraps any registered mode's factory with the 1€ weight filter, so modes
  that arrive later (QP, movement, RBF) get a filtered variant for free.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from livecap.calibration import Profile
from solvers.filters import FilteredSolver, FixedLagSmoother, OneEuroFilter
from solvers.observability import noise_floor, observability, tying_prior
from solvers.regularisation import PriorLeastSquares, estimate_noise, gcv_ridge, holdout_ridge

# Defaults, used when a profile was never tuned (documented in docs/robustness.md).
DEFAULTS = {
    "noise_mm": 0.5,  # marker noise sigma per coordinate, mm
    "prior_sd": 0.3,  # untuned ridge: the MAP ridge (noise / prior_sd)^2 of a N(0, prior_sd^2) weight prior
    "rest_pull": 1.0,  # shapes stay at rest until their evidence exceeds this many noise-floor sds
    "tie": 0.0,  # strength of the tying prior on nearly indistinguishable pairs (x ridge)
    "min_cutoff": 1.0,  # 1€ filter on weights, Hz
    "beta": 30.0,  # 1€ speed coefficient, per (weight unit / s)
    "d_cutoff": 1.0,  # 1€ derivative cutoff, Hz
    "lag": 4,  # fixed-lag smoother latency, frames
}


def robust_settings(profile: Profile, options: dict | None = None) -> dict:
    """Tuned values from the profile, overridden by ``options``, falling back to DEFAULTS."""
    out = dict(DEFAULTS)
    out.update(profile.settings.get("robust", {}))
    out.update({k: v for k, v in (options or {}).items() if k in DEFAULTS or k == "ridge"})
    if "ridge" not in out:
        out["ridge"] = (out["noise_mm"] / out["prior_sd"]) ** 2
    return out


def tune_profile(profile: Profile, targets: np.ndarray, valid: np.ndarray, rate: float) -> dict:
    """Select the noise level and ridge from a take's stabilised displacements; store in the profile.

    Deterministic: the folds, frame thinning and grid are fixed. Returns the stored dict.
    """
    noise = estimate_noise(targets, valid)
    held = holdout_ridge(profile.basis, targets, valid, lower=profile.lower, upper=profile.upper)
    gcv = gcv_ridge(profile.basis, targets, valid)
    tuned = {"noise_mm": noise, "ridge": held.value, "ridge_gcv": gcv.value, "rate": float(rate),
             "criterion": held.criterion}
    profile.settings["robust"] = tuned
    profile.settings.setdefault("noise_mm", noise)
    profile.settings.setdefault("ridge_selected", held.value)
    return tuned


def prior_solver(profile: Profile, options: dict | None = None) -> PriorLeastSquares:
    """The per-frame fit: selected ridge, noise-floor rest-pull, optional tying prior."""
    s = robust_settings(profile, options)
    B = profile.basis
    ridge = float(s["ridge"])
    H = B.T @ B + ridge * np.eye(B.shape[1])
    pull = 2.0 * float(s["rest_pull"]) * noise_floor(B, float(s["noise_mm"]), ridge) * np.diag(H)
    prior = None
    if s["tie"] > 0:
        prior = tying_prior(observability(B, profile.names, float(s["noise_mm"])), float(s["tie"]) * ridge)
    return PriorLeastSquares(B, profile.lower, profile.upper, ridge, prior=prior, rest_pull=pull)


def weight_filter(profile: Profile, options: dict | None = None) -> OneEuroFilter:
    s = robust_settings(profile, options)
    rate = float((options or {}).get("rate", profile.settings.get("robust", {}).get("rate", 120.0)))
    return OneEuroFilter(rate, s["min_cutoff"], s["beta"], s["d_cutoff"])


def robust_solver(profile: Profile, options: dict | None = None) -> FilteredSolver:
    """Streaming: prior fit + 1€ filter on the weights (no fixed latency)."""
    return FilteredSolver(prior_solver(profile, options), weight_filter=weight_filter(profile, options))


def smooth_solver(profile: Profile, options: dict | None = None) -> LookaheadSolver:
    """Lookahead / offline: prior fit + fixed-lag smoother; ``latency_frames`` = lag when streamed."""
    s = robust_settings(profile, options)
    return LookaheadSolver(prior_solver(profile, options), weight_filter=FixedLagSmoother(int(s["lag"])))


class LookaheadSolver(FilteredSolver):
    """``step``: streamed with ``lag`` frames of lookahead (output is frame t - lag);
    ``solve``: the whole take, the smoother centred on every frame (no latency offline)."""

    def solve(self, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
        self.inner.reset()
        W = np.array([self.inner.step(targets[t], valid[t]) for t in range(len(targets))])
        return np.clip(self.weight_filter.filter(W), self.lower, self.upper)


def filtered(factory: Callable) -> Callable:
    """Any mode's factory, with the 1€ filter on its weights (offline ``solve`` is filtered too)."""

    def build(profile: Profile, options: dict | None = None):
        inner = factory(profile, options or {})
        filt = weight_filter(profile, options)
        if hasattr(inner, "solve"):
            return _OfflineFiltered(inner, filt, profile.lower, profile.upper)
        return FilteredSolver(inner, weight_filter=filt, lower=profile.lower, upper=profile.upper)

    return build


class _OfflineFiltered(FilteredSolver):
    def solve(self, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
        W = self.inner.solve(targets, valid)
        return np.clip(self.weight_filter.filter(W), self.lower, self.upper)


ROBUST_MODES: dict[str, Callable] = {"robust": robust_solver, "robust-lag": smooth_solver}
