"""Shapes the markers cannot see stay quiet in every mode (issue 35.3).

When a solver is prepared, ``solvers.observability.quiet_shapes`` names the shapes that the calibrated basis
cannot tell apart from noise (at the profile's measured noise, which includes what the rig cannot explain:
``livecap.modes.robust.tune_profile``) and from the non-negative blends of the other shapes. The mode is then
built on the other shapes only, so a misfit the rig cannot explain stays in the residual instead of being
absorbed by eye gaze or frowns; a nearly parallel partner carries the motion the two shared. The held shapes are
published at rest, or with an animation prior at its conditional mean given the solved shapes (the Gaussian's
regression, clipped to the limits). Modes built from key pairs (``keys``: rbf, qp's actor basis) solve every
shape and have the held ones overwritten the same way. Option ``quiet: false`` turns this off.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from livecap.calibration.animation_prior import AnimationPrior, prior_from_spec
from livecap.calibration.profile import Profile
from solvers.observability import quiet_shapes

log = logging.getLogger(__name__)


class QuietShapes:
    """A mode solving the ``keep`` shapes (or all, ``reduced`` False), published with the ``held`` ones filled."""

    def __init__(self, inner, m: int, keep: np.ndarray, held: np.ndarray, fill: Callable[[np.ndarray], np.ndarray],
                 reduced: bool) -> None:
        self.inner, self.m, self.keep, self.held, self.fill, self.reduced = inner, m, keep, held, fill, reduced
        if hasattr(inner, "solve"):  # a streaming-only mode stays streaming-only (callers test hasattr)
            self.solve = self._solve

    def _full(self, W: np.ndarray) -> np.ndarray:
        W = np.asarray(W, dtype=float)
        kept = W[..., self.keep] if not self.reduced else W
        out = np.empty((*W.shape[:-1], self.m))
        out[..., self.keep] = kept
        out[..., self.held] = self.fill(kept)
        return out

    def step(self, *args, **kwargs) -> np.ndarray:
        return self._full(self.inner.step(*args, **kwargs))

    def _solve(self, *args, **kwargs) -> np.ndarray:
        return self._full(self.inner.solve(*args, **kwargs))

    def __getattr__(self, name: str):  # latency_frames, edit, reset ... of the inner mode
        return getattr(self.inner, name)


def _fill(profile: Profile, keep: np.ndarray, held: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    lo, hi = profile.lower[held], profile.upper[held]
    prior = profile.prior
    if prior is None:
        rest = np.clip(0.0, lo, hi)
        return lambda kept: np.broadcast_to(rest, (*np.shape(kept)[:-1], len(held)))
    S, mu = np.asarray(prior.cov), np.asarray(prior.mean)
    A = np.linalg.solve(S[np.ix_(keep, keep)], S[np.ix_(keep, held)]).T  # held x keep regression
    c = mu[held] - A @ mu[keep]
    return lambda kept: np.clip(np.asarray(kept) @ A.T + c, lo, hi)


def reduced_profile(profile: Profile, keep: np.ndarray) -> Profile:
    """The profile over the ``keep`` shapes (the prior marginalised onto them)."""
    prior = profile.prior
    if prior is not None:
        prior = AnimationPrior(tuple(prior.names[i] for i in keep), np.asarray(prior.mean)[keep],
                               np.asarray(prior.cov)[np.ix_(keep, keep)], prior.frames, prior.sources)
    return replace(profile, names=[profile.names[i] for i in keep], basis=profile.basis[:, keep],
                   lower=profile.lower[keep], upper=profile.upper[keep], prior=prior, marker_rig=None)


def build_quiet(factory: Callable, profile: Profile, options: dict, reduce: bool = True):
    """``factory(profile, options)``, with the shapes the markers cannot see held (module docstring); ``reduce``
    False for modes built from key pairs over every shape (they solve all, the held ones are overwritten)."""
    noise = profile.settings.get("robust", {}).get("noise_mm")
    if noise is None or options.get("quiet") is False:
        return factory(profile, options)
    held = quiet_shapes(profile.basis, float(noise))
    if not len(held):
        return factory(profile, options)
    keep = np.setdiff1d(np.arange(len(profile.names)), held)
    log.info("held %s: the markers cannot tell them from noise at %.3g mm (option quiet=false solves them)",
             ", ".join(profile.names[i] for i in held), noise)
    spec = options.get("prior")
    if spec is not None and not (isinstance(spec, str) and spec in ("shapes", "none", "profile")):
        given = prior_from_spec(spec, profile.prior)
        if isinstance(given, AnimationPrior):  # a prior passed as an option: carried by the profile from here on
            given.check(profile.names)
            profile, options = replace(profile, prior=given), {**options, "prior": "profile"}
    if isinstance(spec, str) and spec == "none":
        profile = replace(profile, prior=None)
    inner = factory(reduced_profile(profile, keep) if reduce else profile, options)
    return QuietShapes(inner, len(profile.names), keep, held, _fill(profile, keep, held), reduce)
