"""Shapes the markers cannot see stay quiet in every mode (issue 35.3).

When a solver is prepared, ``solvers.observability.quiet_shapes`` names the shapes that the calibrated basis
cannot tell apart from noise (at the profile's measured noise, which includes what the rig cannot explain:
``livecap.modes.robust.tune_profile``) and from the non-negative blends of the other shapes. The mode is then
built on the other shapes only, so a misfit the rig cannot explain stays in the residual instead of being
absorbed by eye gaze or frowns; a nearly parallel partner carries the motion the two shared. The held shapes are
published at rest, or with an animation prior at its conditional mean given the solved shapes (the Gaussian's
regression, clipped to the limits). Modes built from key pairs (``keys``: rbf, qp's actor basis) solve every
shape and have the held ones overwritten the same way. Option ``quiet: false`` turns this off.

When calibration measured model mismatch (the rig leaves far more unexplained than the markers' jitter: a real
actor, smoothed data), a shape that is nearly a blend of partners takes up the partners' mismatch (issue 35.1:
mouthFrown rises with the jaw shapes, eyeLookIn with the blink). Every solved weight is then trusted only as far as
the markers move along what its shape alone explains (its signature's part outside the cone of the others',
in the per-marker noise calibration measured, ``solvers.observability.unique_evidence``): at rest below 2 noise sd
of that evidence (averaged over 0.16 s), whole above 6 (``EvidenceGate``). The sd is the larger of calibration's and
the one the solve leaves now (its whitened residual over the same 0.16 s: a neutral take does not show what the rig
misses while the actor acts), and the gate's factor moves from rest to whole in no less than 0.32 s (a decision on
a 0.16 s average does not switch within a frame). Same-rig takes with white noise never reach that branch.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from livecap.calibration.animation_prior import AnimationPrior, prior_from_spec
from livecap.calibration.profile import Profile
from solvers.observability import quiet_shapes, unique_evidence, whiten

log = logging.getLogger(__name__)


EVIDENCE_ZERO = 2.0  # a weight whose unique evidence is below this many noise sd is published at rest ...
EVIDENCE_FULL = 6.0  # ... whole above this many, linear between (AnimFace takes; 12 lost on the mismatch takes)
EVIDENCE_SECONDS = 0.16  # time constant of the evidence's causal average (a phantom flickers with single frames)
GATE_SWING_SECONDS = 2 * EVIDENCE_SECONDS  # the gate's factor takes at least this long from 0 to 1 (or back)


class EvidenceGate:
    """Each weight scaled by how far the markers move along what its shape alone explains (issue 35; module
    docstring): 0 below ``EVIDENCE_ZERO`` noise sd, whole above ``EVIDENCE_FULL``. The evidence of shape k in a
    frame is the residual with k's own part put back, along k's unique direction (``unique_evidence``), averaged
    causally over ``EVIDENCE_SECONDS`` (``rate`` Hz; None: per frame) and divided by the residual's own sd over the
    same frames when that exceeds the calibrated noise; the factor then changes by at most ``1 / (rate *
    GATE_SWING_SECONDS)`` a frame. One frame (``step``) or a take (``T x m``).
    Only the ``gated`` shapes are gated and count as each other's partners (a held shape explains nothing)."""

    def __init__(self, basis: np.ndarray, noise_mm: float, marker_noise: np.ndarray | None, gated: np.ndarray,
                 rate: float | None = None) -> None:
        self.B = np.asarray(basis, dtype=float)
        cols = np.flatnonzero(gated)
        self.E = np.zeros((self.B.shape[1], self.B.shape[0]))
        self.E[cols] = unique_evidence(self.B[:, cols], noise_mm, marker_noise)[0]
        self.own = self.E * self.B.T  # each shape's evidence per unit of its own weight, per coordinate
        self.per_mm = whiten(np.ones((self.B.shape[0], 1)), noise_mm, marker_noise)[:, 0]  # 1 / sd per coordinate
        self.gated = gated
        self.keep = float(np.exp(-1.0 / (rate * EVIDENCE_SECONDS))) if rate else 0.0  # the average's memory
        self.slew = 1.0 / (rate * GATE_SWING_SECONDS) if rate else 1.0  # the factor's largest change per frame
        self.last: np.ndarray | None = None  # the averaged evidence, the averaged residual, the factor
        self.last_r: np.ndarray | None = None
        self.g: np.ndarray | None = None

    def reset(self) -> None:
        self.last = self.last_r = None
        self.g = None

    def _limit(self, gate: np.ndarray) -> np.ndarray:
        """The factor moved toward ``gate`` by at most ``slew`` a frame (a decision on a 0.16 s average does not
        switch within a frame: issue 35's cheek-take jumps were weights crossing the ramp in 2-4 frames)."""
        if self.slew >= 1.0:
            return gate
        if gate.ndim == 1:
            if self.g is not None:
                gate = np.clip(gate, self.g - self.slew, self.g + self.slew)
            self.g = gate
            return gate
        out = np.array(gate)
        for i in range(1, len(out)):
            out[i] = np.clip(out[i], out[i - 1] - self.slew, out[i - 1] + self.slew)
        return out

    def __call__(self, W: np.ndarray, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
        Y = np.asarray(targets, dtype=float).reshape(*np.shape(W)[:-1], -1)
        seen = np.repeat(np.asarray(valid, dtype=bool), 3, axis=-1)
        R = np.where(seen, Y - W @ self.B.T, 0.0)  # hidden markers (NaN or stale) say nothing
        t = np.abs(R @ self.E.T + (seen @ self.own.T) * W)
        r2 = np.sum((R * self.per_mm) ** 2, axis=-1, keepdims=True) / np.maximum(seen.sum(-1, keepdims=True), 1)
        if np.ndim(W) == 1:
            t = t if self.last is None else self.keep * self.last + (1.0 - self.keep) * t
            r2 = r2 if self.last_r is None else self.keep * self.last_r + (1.0 - self.keep) * r2
            self.last, self.last_r = t, r2
        elif len(t):  # a whole take: the same average, in one pass
            from scipy.signal import lfilter

            t = lfilter([1.0 - self.keep], [1.0, -self.keep], t, axis=0, zi=self.keep * t[:1])[0]
            r2 = lfilter([1.0 - self.keep], [1.0, -self.keep], r2, axis=0, zi=self.keep * r2[:1])[0]
        t = t / np.sqrt(np.maximum(r2, 1.0))  # in the noise the solve leaves now, never below calibration's
        gate = self._limit(np.clip((t - EVIDENCE_ZERO) / (EVIDENCE_FULL - EVIDENCE_ZERO), 0.0, 1.0))
        return np.where(self.gated, W * gate, W)


class QuietShapes:
    """A mode solving the ``keep`` shapes (or all, ``reduced`` False), published with the ``held`` ones filled and
    the others through the ``gate`` when there is one."""

    def __init__(self, inner, m: int, keep: np.ndarray, held: np.ndarray, fill: Callable[[np.ndarray], np.ndarray],
                 reduced: bool, gate: EvidenceGate | None = None) -> None:
        self.inner, self.m, self.keep, self.held, self.fill, self.reduced = inner, m, keep, held, fill, reduced
        self.gate, self.seen = gate, deque()
        if hasattr(inner, "solve"):  # a streaming-only mode stays streaming-only (callers test hasattr)
            self.solve = self._solve
        if hasattr(inner, "reset"):  # likewise: the live warm-up steps only solvers it can reset
            self.reset = self._reset

    def _full(self, W: np.ndarray, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
        W = np.asarray(W, dtype=float)
        kept = W[..., self.keep] if not self.reduced else W
        out = np.empty((*W.shape[:-1], self.m))
        out[..., self.keep] = kept
        out[..., self.held] = self.fill(kept)
        return out if self.gate is None else self.gate(out, targets, valid)

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        w = self.inner.step(target, valid)
        lag = int(getattr(self.inner, "latency_frames", 0) or 0)
        if self.gate is None or lag == 0:  # the weights are this frame's: nothing to keep
            return self._full(w, target, valid)
        self.seen.append((np.array(target, dtype=float), np.array(valid, dtype=bool)))
        lag = min(lag, len(self.seen) - 1)  # w is of frame t - lag
        while len(self.seen) > lag + 1:
            self.seen.popleft()
        return self._full(w, *self.seen[0])

    def _reset(self) -> None:
        self.inner.reset()
        self.seen.clear()
        if self.gate is not None:
            self.gate.reset()

    def _solve(self, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
        return self._full(self.inner.solve(targets, valid), targets, valid)

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


def marker_noise(profile: Profile) -> np.ndarray | None:
    """The per-marker noise calibration measured (its fit residual, misfit included), when it fits the layout."""
    per = profile.settings.get("robust", {}).get("marker_noise_mm")
    if per is None or len(per) * 3 != profile.basis.shape[0]:
        return None
    return np.asarray(per, dtype=float)


def mismatched(profile: Profile) -> bool:
    """Calibration measured the rig leaving far more unexplained than the markers' jitter (its warning: the actor
    is not the rig, or the data were smoothed; ``livecap.modes.robust.NOISE_DISAGREES``)."""
    from livecap.modes.robust import NOISE_DISAGREES

    tuned = profile.settings.get("robust", {})
    jitter, residual = tuned.get("jitter_mm"), tuned.get("residual_mm")
    return jitter is not None and residual is not None and residual > NOISE_DISAGREES * jitter


def build_quiet(factory: Callable, profile: Profile, options: dict, reduce: bool = True):
    """``factory(profile, options)``, with the shapes the markers cannot see held (module docstring); ``reduce``
    False for modes built from key pairs over every shape (they solve all, the held ones are overwritten)."""
    noise = profile.settings.get("robust", {}).get("noise_mm")
    if noise is None or options.get("quiet") is False:
        return factory(profile, options)
    held = quiet_shapes(profile.basis, float(noise))
    keep = np.setdiff1d(np.arange(len(profile.names)), held)
    gate = None
    if mismatched(profile):
        rest = np.zeros(len(profile.names), bool)
        rest[keep] = (profile.lower[keep] <= 0) & (profile.upper[keep] >= 0)
        gate = EvidenceGate(profile.basis, float(noise), marker_noise(profile), rest,
                            profile.settings.get("robust", {}).get("rate"))
        log.info("the rig leaves more unexplained than the markers' jitter: weights trusted as far as their "
                 "shape's own marker motion is seen above the noise (option quiet=false turns this off)")
    if not len(held) and gate is None:
        return factory(profile, options)
    if len(held):
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
    reduce = reduce and bool(len(held))
    inner = factory(reduced_profile(profile, keep) if reduce else profile, options)
    return QuietShapes(inner, len(profile.names), keep, held, _fill(profile, keep, held), reduce, gate)
