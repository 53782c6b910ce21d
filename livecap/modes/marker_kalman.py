"""``kalman``: constant-velocity Kalman filtering of the markers, then a bounded fit under a prior.

Issue 15 measured that, on real acting, the per-frame solve's error is marker noise that a filter
on the *weights* cannot remove; filtering the *markers* with a constant-velocity model whose noise
comes from the take's own innovation likelihood (solvers.marker_kalman) removes it. Streamed with
one frame of latency (fixed-lag smoothing); offline by the RTS smoother. The fit is the per-frame
bounded QP (Curio et al. 2006 §2.3) with a Gaussian prior on the weights — learned from real
animation (``--prior``, livecap.calibration.animation_prior; Lewis et al. 2014 §7.8-7.9) or, without
one, a ridge — whose strength is chosen by held-out markers on the take (solvers.prior_strength).

The weights then pass an IMM of a 'hold' and a 'move' constant-velocity model (solvers.tracking;
Bar-Shalom et al. 2001 §11.6.6), the ``robust`` mode's weight stage and settings, its measurement
variance per shape the take's marker noise over the shape's marker norm. Issue 15 measured where
the streamed jitter came from (ICT 0.5 mm, S07-001 and apfel): the filtered markers' residual noise
through the ill-conditioned basis (jitter 13 x / 6 x the truth's; the per-frame strength switching
adds about a tenth), not the pose re-fit; the IMM cuts it to 3.3 x / 2.2 x at no weight RMSE cost
and no added lag (it holds while innovations look like noise and follows at once when they do not).
Offline the IMM runs forwards and backwards and the two are averaged (zero phase).

Streamed cost (issue 15): the marker bank runs over q / r only (solvers.marker_kalman), the held-out
strength is tried every STRENGTH_TRIAL_EVERY-th frame, and the pose alternation starts from 0.3 of
the last frame's correction with one re-fit (solvers.pose_refine.StreamingPoseRefit): two QP solves
and one rigid fit a frame plus half a trial, instead of four solves and two fits; 2.1-2.8 x less
thread CPU at 60 markers (docs/robustness.md, "`kalman` streamed cost").
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livecap.calibration.animation_prior import AnimationPrior
from livecap.calibration.profile import Profile
from livecap.modes.robust import robust_settings
from solvers.marker_kalman import KalmanSettings, StreamingMarkerKalman, smooth_take
from solvers.pose_refine import StreamingPoseRefit, refit_pose
from solvers.prior_strength import HeldOutStrength
from solvers.qp import FrameQP
from solvers.tracking import IMMFilter, dwna_variance

STRENGTHS = np.logspace(-3, 1, 9)  # prior weight, mm^2 (the marker variance it balances)
STREAM_HALF_LIFE_FRAMES = 600.0  # memory of the streaming held-out choice
STRENGTH_TRIAL_EVERY = 2  # streaming: frames per held-out strength trial (4: demo take RMSE +13 %, see docs)
POSE_CARRY = 0.3  # streaming: the part of the last frame's pose correction that starts the next (pose_refine)
POSE_REFITS = 2  # offline pose/expression alternations (issue 15: ICT 0.2 mm vertex p95 0.66 -> 0.43 -> 0.35 mm)


@dataclass(frozen=True)
class WeightMotion:
    """The IMM weight stage: acceleration sds (weight units / s^2) and mean sojourn (s) at ``rate`` Hz."""

    rate: float
    hold_accel: float
    move_accel: float
    sojourn: float

    def imm(self, noise_mm: float, norms: np.ndarray) -> IMMFilter:
        return IMMFilter(dwna_variance(self.hold_accel, self.rate), dwna_variance(self.move_accel, self.rate),
                         noise_mm**2 / norms**2, sojourn_frames=max(2.0, self.sojourn * self.rate))


class MarkerKalmanSolver:
    """``step``: filtered markers of frame t - 1 -> weights (``latency_frames`` = 1);
    ``solve``: the whole take RTS-smoothed -> weights per frame."""

    latency_frames = 1

    def __init__(self, profile: Profile, mean: np.ndarray, precision: np.ndarray, settings: KalmanSettings,
                 motion: WeightMotion) -> None:
        self.profile, self.mean, self.precision, self.settings = profile, mean, precision, settings
        self.motion = motion
        self.norms = np.maximum(np.linalg.norm(profile.basis, axis=0), 1e-9)
        self.lower, self.upper = profile.lower, profile.upper
        self.filter = StreamingMarkerKalman(profile.n_markers, settings, lag=self.latency_frames)
        self.pose = StreamingPoseRefit(profile.source_neutral, profile.stable, profile.basis)
        self.chosen: dict = {}
        self.reset()

    def _selector(self, decay: float) -> HeldOutStrength:
        return HeldOutStrength(self.profile.basis, self.lower, self.upper, self.mean, self.precision, STRENGTHS,
                               decay=decay)

    def _fit(self, k: int) -> FrameQP:
        if k not in self._fits:
            self._fits[k] = FrameQP(self.profile.basis, self.lower, self.upper, prior=(self.mean, self.precision),
                                    prior_weight=float(STRENGTHS[k]))
        return self._fits[k]

    def reset(self) -> None:
        self.filter.reset()
        self.pose.reset()
        self.selector = self._selector(0.5 ** (STRENGTH_TRIAL_EVERY / STREAM_HALF_LIFE_FRAMES))
        self._frame = 0
        self._fits: dict[int, FrameQP] = {}
        self._imm: tuple[float, IMMFilter] | None = None
        for k in range(len(STRENGTHS)):  # build every workspace now, not on the first frames
            self._fit(k).step(np.zeros(3 * self.profile.n_markers), np.ones(self.profile.n_markers, bool))
            self._fits[k].reset()

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        x, ok = self.filter.step(target, valid)
        if self._frame % STRENGTH_TRIAL_EVERY == 0:
            self.selector.observe(x, ok)
        self._frame += 1
        fit = self._fit(self.selector.best)
        w = fit.step(self.pose.apply(x, ok, POSE_CARRY), ok)
        w = fit.step(self.pose.refit(x, ok, w), ok)
        noise = self.filter.noise_mm
        if self._imm is None or self._imm[0] != noise:  # noise settles in the first frames; rarely changes after
            self._imm = (noise, self.motion.imm(noise, self.norms))
        return self._imm[1].step(w)

    def solve(self, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """RTS-smoothed markers -> prior fit; then POSE_REFITS times: head pose re-fitted on the smoothed
        markers to the stable markers the expression predicts (solvers.pose_refine), applied to the raw
        markers, smoothed and solved again; last the IMM forwards and backwards, averaged."""
        p = self.profile
        valid = np.asarray(valid, bool)
        d = np.asarray(targets, float)
        for i in range(POSE_REFITS + 1):
            W, smoothed = self._solve_once(d, valid)
            if i < POSE_REFITS:
                d = refit_pose(d, valid, W, p.source_neutral, p.stable, p.basis, pose_from=smoothed)
        noise = self.chosen["noise_mm"]
        forward = self.motion.imm(noise, self.norms).filter(W)
        backward = self.motion.imm(noise, self.norms).filter(W[::-1])[::-1]
        return 0.5 * (forward + backward)

    def _solve_once(self, targets: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        smoothed, ok, self.chosen = smooth_take(targets, valid, self.settings)
        sel = self._selector(1.0)
        for t in range(len(targets)):
            sel.observe(smoothed[t], ok[t])
        self.chosen["prior_weight"] = float(STRENGTHS[sel.best])
        fit = self._fit(sel.best)
        fit.reset()
        return np.array([fit.step(smoothed[t], ok[t]) for t in range(len(targets))]), smoothed

def animation_prior_option(options: Mapping | None) -> AnimationPrior | None:
    """The animation prior an option ``prior`` gives (an AnimationPrior or the path of one, .npz), else
    None (movement's ``prior`` values -- 'shapes', 'none', weight curves -- are not animation priors)."""
    prior = (options or {}).get("prior")
    if isinstance(prior, str | Path) and str(prior).endswith(".npz"):
        return AnimationPrior.load(prior)
    return prior if isinstance(prior, AnimationPrior) else None


def kalman_mode(profile: Profile, options: Mapping | None = None) -> MarkerKalmanSolver:
    """Option ``prior`` (AnimationPrior or its path; default the profile's, else a ridge); ``rate`` (Hz;
    default the profile's tuned rate, else the robust modes' default) sets the IMM's per-frame process noise."""
    options = options or {}
    prior = animation_prior_option(options) or profile.prior
    if prior is None:
        mean, precision = np.zeros(len(profile.names)), np.eye(len(profile.names))
    else:
        prior.check(profile.names)
        mean, precision = prior.mean, np.linalg.inv(prior.cov)
    r = robust_settings(profile, {"rate": options.get("rate")})
    motion = WeightMotion(float(r.rate), float(r.hold_accel), float(r.move_accel), float(r.sojourn))
    return MarkerKalmanSolver(profile, mean, precision, KalmanSettings(), motion)
