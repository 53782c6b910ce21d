"""``kalman``: constant-velocity Kalman filtering of the markers, then a bounded fit under a prior.

Issue 15 measured that, on real acting, the per-frame solve's error is marker noise that a filter
on the *weights* cannot remove; filtering the *markers* with a constant-velocity model whose noise
comes from the take's own innovation likelihood (solvers.marker_kalman) removes it. Streamed with
one frame of latency (fixed-lag smoothing); offline by the RTS smoother. The fit is the per-frame
bounded QP (Curio et al. 2006 §2.3) with a Gaussian prior on the weights — learned from real
animation (``--prior``, livecap.calibration.animation_prior; Lewis et al. 2014 §7.8-7.9) or, without
one, a ridge — whose strength is chosen by held-out markers on the take (solvers.prior_strength).

The weights then pass an IMM of a 'hold' and a 'move' constant-velocity model (solvers.tracking;
Bar-Shalom et al. 2001 §11.6.6), the ``robust`` mode's weight stage and settings. Its measurement noise
is the marker noise (the marker filter's estimate, never under the calibrated noise) through the fit: the
fit's whole weight covariance (noise^2 x the inverse Hessian), the IMM run along its eigenvectors
(solvers.tracking.RotatedIMM; issue 41 measured jitter, weight RMSE and vertex p95 all lower, streamed and
offline, than with a variance per shape). One IMM a take, its noise changed in place. Streamed, each direction's
output is then pulled toward its running mean where the stream shows it carries mostly noise (solvers.tracking.
NoiseShrink; issue 41: ICT 0.2 mm weight RMSE 0.53 -> 0.49 x the oracle, jitter and blinks kept). Issue 15 measured
where the streamed jitter came from (ICT 0.5 mm, S07-001 and apfel): the filtered markers' residual noise
through the ill-conditioned basis (jitter 13 x / 6 x the truth's;
the per-frame strength switching adds about a tenth), not the pose re-fit; the IMM cuts it to 3.3 x /
2.2 x at no weight RMSE cost and no added lag (it holds while innovations look like noise and follows
at once when they do not).
Offline the IMM runs forwards and backwards and the two are averaged (zero phase).

The stabiliser's residual head-pose error is fitted with the expression: six linearised rigid
columns beside the basis, unbounded and outside the prior, in the same QP (solvers.pose_refine).
Issue 15 (ICT, six real performances, ``livecap realeval``): against the Kabsch/solve alternation it
replaced, streamed vertex p95 1.02 -> 0.79 x the oracle at 0.5 mm, offline 0.71 -> 0.43 x; with the
stream's hidden markers dropped after 2 frames (solvers.marker_kalman) as well, streamed 0.66 x at
0.5 mm and 1.50 -> 0.72 x at 0.2 mm. Offline, the pose fitted on the smoothed markers is undone on the
raw ones and the take smoothed and solved again (POSE_PASSES), so the smoother's noise choice does
not see the pose error.

Streamed cost (issue 15): the marker bank runs over q / r only (solvers.marker_kalman), the held-out
strength is tried every STRENGTH_TRIAL_EVERY-th frame, and pose and expression are one QP solve: one
solve a frame plus half a trial (docs/robustness.md, "`kalman` streamed cost", "joint pose").
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from livecap.calibration.animation_prior import AnimationPrior, prior_from_spec
from livecap.calibration.profile import Profile
from livecap.modes.robust import robust_settings
from solvers.marker_kalman import KalmanSettings, StreamingMarkerKalman, smooth_take
from solvers.pose_refine import RigidColumns
from solvers.prior_strength import HeldOutStrength, take_strength
from solvers.prior_support import Support, evidence_strength, widen_prior
from solvers.qp import MARKER_SPACE_RATIO, FrameQP
from solvers.tracking import IMMFilter, NoiseShrink, RotatedIMM, dwna_variance, variances_along

STRENGTHS = np.logspace(-3, 1, 9)  # prior weight, mm^2 (the marker variance it balances)
STREAM_PASSES = 1  # streaming, marker-space fits and trials (72 x 1000): block-pivoting passes a frame (0: exact;
# docs/performance.md, "`kalman` at 72 x 1000: one block-pivoting pass a frame"); offline solves are exact
STREAM_HALF_LIFE_FRAMES = 600.0  # memory of the streaming held-out choice
STRENGTH_TRIAL_EVERY = 2  # streaming: frames per held-out strength trial (4: demo take RMSE +13 %, see docs)
TRIAL_LATE_FRAMES = 2  # streaming: frames a trial part may wait while the fit meets new visibility patterns
POSE_PASSES = 2  # offline: joint solves, the pose undone on the raw markers between (3: no better, issue 15)
SUPPORT_SECONDS = 1.0  # streaming: the first seconds a prior is checked against (solvers.prior_support)
UNCHECKED_SPREAD = 2.0  # a prior not yet checked: its covariance times this (see MarkerKalmanSolver.__init__)
SUPPORT_FRAMES = 120  # streaming: at most this many frames, evenly spread, for the check (cost ~ frames)
# offline: the same over the whole take (issue 39: 120 -> 60 halved the check, ~0.1 s of a 30 s take; realeval's
# offline rows within 1 % either way, docs/performance.md)
SUPPORT_TAKE_FRAMES = 60
# offline: the check's iterations stop when no variance moves by more than this (relative) nor the mean by more than
# this many sds. The variances are not used (only the mean, solvers.prior_support), and they are what converges
# slowly: 0.01 -> 0.1 took 19 -> 6 / 7 iterations on S07-001 / apfel (0.12-0.13 -> 0.04-0.05 s) and moved the mean by
# 0.006 / 0.001 sd at most (issue 39 item 2, docs/performance.md)
SUPPORT_TAKE_TOL = 0.1
SUPPORT_SWAP = 0.5  # streaming: the check runs in a thread meanwhile; its prior is used this share of its window later
SUPPORT_SWAP_MAX = 1.0  # streaming: ... or this many seconds later if sooner (a check costs the same on any window)
SUPPORT_GROWTH = 2.0  # streaming: checked again on the take so far each time it is this many times the last window
# streaming: half-life of the marker bank's likelihoods, so each marker's q follows a blink's onset as the offline
# smoother's local choice does (issue 41, MakeHuman 0.5 mm: 10 s memory kept 0.84 of the blinks' peaks, 0.4 s 0.90)
MARKER_MEMORY_SECONDS = 0.4
SHRINK_WARM_SECONDS = 1.0  # streaming: the weight stage's pull toward each direction's mean starts after this much
SHRINK_MEMORY_SECONDS = 60.0  # ... and reads its mean, spread and noise over about this much (solvers.tracking)
SHARED_MOVE = 0.3  # streaming: every direction's 'move' probability at least this x the largest (RotatedIMM share)


log = logging.getLogger(__name__)


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

    def shrink(self) -> NoiseShrink:
        return NoiseShrink(warm_frames=max(2, int(SHRINK_WARM_SECONDS * self.rate)),
                           half_life_frames=SHRINK_MEMORY_SECONDS * self.rate)


class MarkerKalmanSolver:
    """``step``: filtered markers of frame t - 1 -> weights (``latency_frames`` = 1);
    ``solve``: the whole take RTS-smoothed -> weights per frame. ``head_correction``: the residual head
    motion fitted with the last streamed frame (solvers.pose_refine: translation mm, rotation mm of arc)."""

    latency_frames = 1

    def __init__(self, profile: Profile, mean: np.ndarray, precision: np.ndarray, settings: KalmanSettings,
                 motion: WeightMotion, prior_cov: np.ndarray | None = None) -> None:
        """``prior_cov``: an animation prior's covariance (``precision`` its inverse), checked against the take: its
        mean re-centred where the frames say the actor rests elsewhere (solvers.prior_support); None for the ridge,
        which is not checked."""
        if prior_cov is not None:
            # before any frame is checked this actor's mean is unknown, distributed as the prior itself (the check's
            # hyperprior, solvers.prior_support): a frame's prior is N(mean, cov + cov); each check narrows it
            precision = precision / UNCHECKED_SPREAD
        self.profile, self.mean, self.precision, self.settings = profile, mean, precision, settings
        self.motion = motion
        self.prior_cov, self._precision0, self._mean0 = prior_cov, precision, mean
        self.support: Support | None = None
        self.norms = np.maximum(np.linalg.norm(profile.basis, axis=0), 1e-9)
        # the weight stage's noise floor: what calibration measured the rig cannot explain (issue 35.2); the marker
        # filter's own estimate starts small and reads only the jitter of a smoothed capture
        self.calibrated_noise = float(profile.settings.get("robust", {}).get("noise_mm") or 0.0)
        self.pose = RigidColumns(profile.source_neutral)
        self.m = len(profile.names)
        self.lower, self.upper = profile.lower, profile.upper
        self.joint = self.pose.augment(profile.basis, profile.lower, profile.upper, mean, precision)  # B, limits, prior
        self.filter = StreamingMarkerKalman(profile.n_markers, settings, lag=self.latency_frames)
        self.chosen: dict = {}
        self._pool: ThreadPoolExecutor | None = None  # streaming: the prior check's thread (``_pool_here``)
        self._pool_pid = 0
        self.reset()

    def _selector(self, decay: float) -> HeldOutStrength:
        return _selector(self.joint, decay, self.prior_cov is not None)

    def _fit(self, k: int) -> FrameQP:
        if k not in self._fits:
            B, lower, upper, mean, precision = self.joint
            self._fits[k] = FrameQP(B, lower, upper, prior=(mean, precision), prior_weight=float(STRENGTHS[k]),
                                    like=next(iter(self._fits.values()), None), frame_passes=STREAM_PASSES)
        return self._fits[k]

    def _spread_of(self, k: int) -> np.ndarray:
        """The weights' covariance per unit marker variance in the fit at strength ``k`` (m x m): the weights'
        block of the inverse Hessian, the head-pose columns fitted beside them marginalised."""
        if k not in self._spreads:
            B, _, _, _, P = self.joint
            self._spreads[k] = _weight_cov(B, P, STRENGTHS[k], self.m)
        return self._spreads[k]

    def _check_support(self, targets: np.ndarray, valid: np.ndarray, noise_mm: float) -> None:
        """Re-centre the prior where the frames' marginal likelihood says the actor rests elsewhere, widen it where
        they say the actor moves beyond it, and say so (a whole take: to SUPPORT_TAKE_TOL; the streamed selector is
        left as it was, a stream after :meth:`solve` starts with ``reset``). Offline only: the widened directions
        loosen the fit, the strength is still chosen on the prior as re-centred (:meth:`_solve_once`), so a take
        that sweeps a direction the prior's performers barely used (issue 41.2, alex_rom_4's eye contrasts: 4-11 x
        the prior's variance) is no longer held to it (docs/robustness.md, "alex_rom_4 and its own performer's
        prior")."""
        self._use_support(self._support(targets, valid, noise_mm, SUPPORT_TAKE_TOL, outside=1.0), len(targets))

    def _support(self, targets: np.ndarray, valid: np.ndarray, noise_mm: float, tol: float = 1e-2,
                 outside: float = np.inf) -> Support:
        return widen_prior(self.profile.basis, self._mean0, self.prior_cov, targets, valid, self.lower, self.upper,
                           extra=self.pose.matrix, noise_var=noise_mm**2, tol=tol, outside=outside)

    def _use_support(self, s: Support, frames: int = 0, built: tuple | None = None) -> None:
        """Use the checked prior ``s`` (of ``frames`` frames); ``built``: what :meth:`_build` made of it in the check's
        thread (its notes worded there), so that the step only swaps references (the rest is built here)."""
        self.support = s
        unchanged, notes = self._notes(s, frames) if built is None else built[-1]
        kept = unchanged and self.precision is self._precision0 and self.mean is self._mean0
        if built is None:
            _say(notes)
            if kept:
                return
            self.mean, self.precision = s.mean, s.precision
            self.joint = self.pose.augment(self.profile.basis, self.lower, self.upper, self.mean, self.precision)
            # (a whole take's check, :meth:`_check_support`: the streamed selector is not rebuilt, the offline solve's
            # strength is take_strength's; ``reset`` builds it for a stream; issue 39 item 2: ~20 ms of a 30 s take)
            self._fits, self._spreads, self._along = {}, {}, {}
            self._noise_key = None
            return
        old = []
        if not kept:
            old = [self._fits, self.selector]
            self.mean = s.mean
            self.joint, self._fits, self._spreads, self.selector, self._along, self.precision = built[:6]
            self.selector.carry(old[1])
            self._noise_key = None
        # the log's lines and the old fits and selector's release on the check's thread, right after this frame: on
        # a back-to-back stream's swap frame, its caches cold after waiting for the check, they cost ~0.12-0.14 ms and
        # ~0.4 ms (issue 39)
        self._pool_here().submit(_say, notes, old)

    def _notes(self, s: Support, frames: int) -> tuple[bool, list[tuple[int, str]]]:
        """Whether the check left the prior as it was, and what to log of it (streamed: worded in the check's
        thread, logged at the swap)."""
        wide = s.widened
        moved = s.mean - self._mean0
        sd = np.sqrt(np.diag(self.prior_cov))
        far = np.flatnonzero(np.abs(moved) > sd)  # said only where it is news: beyond one of the prior's sds
        unchanged = not len(wide) and not np.any(moved)
        notes = []
        if unchanged:
            notes.append((logging.INFO, f"animation prior: the actor's activity lies inside it ({frames} frames)"))
        if len(wide):
            top = np.argsort(-s.added_per_shape())[:3]
            notes.append((logging.WARNING, f"animation prior widened along {len(wide)} of {len(s.before)} directions, "
                          f"most in {', '.join(self.profile.names[i] for i in top)}: the actor's activity lies "
                          "outside it"))
        if len(far):
            top = far[np.argsort(-np.abs(moved[far]) / sd[far])][:3]
            notes.append((logging.WARNING, f"animation prior re-centred on the actor ({frames} frames): " + ", ".join(
                f"{self.profile.names[i]} {self._mean0[i]:.2f} -> {s.mean[i]:.2f}" for i in top)))
        return unchanged, notes

    def _build(self, s: Support, decay: float, frames: int, imm: RotatedIMM | None) -> tuple:
        """The joint prior, every strength's fit (its all-seen workspace warmed, as ``reset`` does), the weights'
        spreads (and along ``imm``'s axes), a fresh selector, the precision and the log's notes for the checked
        prior ``s``, built without touching the solver: streamed, the check's thread builds them, so the swap costs
        the step nothing (built at the swap they took 10-23 ms; the precision, the notes and the spreads along the
        axes another ~0.2 ms, issue 39)."""
        precision = s.precision
        joint = self.pose.augment(self.profile.basis, self.lower, self.upper, s.mean, precision)
        selector = _selector(joint, decay, True)
        fits, spreads = _warmed_fits(joint, self.profile.n_markers, self.m, selector.qps[0])
        along = {} if imm is None else {k: imm.along(c) for k, c in spreads.items()}
        return joint, fits, spreads, selector, along, precision, self._notes(s, frames)

    def _stream_support(self, x: np.ndarray, ok: np.ndarray) -> None:
        """Keep the take's frames (at most 2 x SUPPORT_FRAMES, thinned evenly as it grows), check them in a thread
        after SUPPORT_SECONDS and again each time the take is SUPPORT_GROWTH times as long (numpy's inverses
        release the GIL, so the frames keep coming), each check from the prior as given on the take so far; use
        each result SUPPORT_SWAP x its window later, at most SUPPORT_SWAP_MAX (a check of at most SUPPORT_FRAMES and
        its fits take ~0.5-0.7 s on a loaded 2-core VM: a fixed 0.5 s made the step wait up to 98 ms for the 2 and
        4 s checks), always at the same frame, so a streamed solve is reproducible
        (it waits there only if the check has not finished)."""
        if self._offered % self._stride == 0:
            self._seen.append((x.reshape(-1).copy(), ok.copy()))
            if len(self._seen) > 2 * SUPPORT_FRAMES:
                self._seen, self._stride = self._seen[::2], 2 * self._stride
        self._offered += 1
        if self._pool is None:
            self._pool_here()
        if self._checking is None and self._offered >= self._next_check * self.motion.rate:
            later = max(1, int(min(SUPPORT_SWAP * self._next_check, SUPPORT_SWAP_MAX) * self.motion.rate))
            self._next_check *= SUPPORT_GROWTH
            # the frames kept so far (never changed once kept): picked and stacked in the check's thread
            job = self._pool_here().submit(self._check, self._seen[:], self.filter.noise_mm, self.selector.decay,
                                           self._imm)
            self._checking = (job, self._frame + later)

    def _pool_here(self) -> ThreadPoolExecutor:
        """The check's pool of this process, its thread started before the frame of the first check (~0.15 ms, issue
        39); a forked process has its parent's pool but not its thread, and starts its own."""
        if self._pool is None or self._pool_pid != os.getpid():
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="livecap-prior-check")
            self._pool.submit(int)
            self._pool_pid = os.getpid()
        return self._pool

    def _check(self, seen: list, noise_mm: float, decay: float, imm: RotatedIMM | None) -> list:
        """The check's thread: at most SUPPORT_FRAMES of the frames ``seen``, evenly spread, checked; the checked
        prior and what :meth:`_build` makes of it (its errors reach ``_swap`` through the job)."""
        pick = _spread(len(seen), SUPPORT_FRAMES)
        s = self._support(np.stack([seen[i][0] for i in pick]), np.stack([seen[i][1] for i in pick]), noise_mm)
        return [s, self._build(s, decay, len(pick), imm)]

    def _swap(self) -> None:
        """At the start of the frame a check's prior is due: it is used, its thread joined if not done. Where the
        frames come faster than the check (a back-to-back benchmark) the thread waits here and the frame after the
        wait runs with its caches cold; swapped at the end of the step before (so that its next workspace was built
        on the new fits), two frames paid for it, each in kalman's top 1 % (issue 39, docs/performance.md). A check
        begun by the process this one was forked from never finishes here (its thread is not here): it counts as
        failed."""
        job, _ = self._checking
        self._checking = None
        try:
            if self._pool_pid != os.getpid():
                raise RuntimeError("the process was forked while its prior was being checked")
            out = job.result()
        except Exception as e:  # noqa: BLE001 - a stream must survive its check's failure
            out = [e]
        if len(out) == 2 and isinstance(out[0], Support):
            self._use_support(out[0], built=out[1])
            return
        log.warning("animation prior: its check against the actor failed (%s); kept as it is", out[:1])
        self._next_check, self._seen = float("inf"), []
        if self.support is None:
            lam, axes = np.linalg.eigh(self.prior_cov)
            self.support = Support(axes, lam, lam, float("nan"), 0, self._mean0)

    def _prior_as_given(self) -> None:
        """A new take: the prior as given, to be checked against this take."""
        if self.support is not None and (self.precision is not self._precision0 or self.mean is not self._mean0):
            self.precision, self.mean = self._precision0, self._mean0
            self.joint = self.pose.augment(self.profile.basis, self.lower, self.upper, self.mean, self.precision)
            self._fits, self._spreads, self._along = {}, {}, {}
            self._noise_key = None
        self.support = None
        self._seen: list[tuple[np.ndarray, np.ndarray]] = []  # streaming: every ``_stride``-th frame of the take
        self._offered, self._stride = 0, 1
        self._checking: tuple | None = None  # streaming: the check's job and the frame to use its prior
        self._next_check = SUPPORT_SECONDS  # streaming: the take's length (s) at which it is checked next

    def reset(self) -> None:
        self._prior_as_given()
        self.filter.reset()
        self.head_correction = np.zeros(6)
        self.selector = self._selector(0.5 ** (1.0 / STREAM_HALF_LIFE_FRAMES))  # per frame (``_trial``)
        self._frame = 0
        self._due = self._last_trial = 0  # the frame the next strength trial is due, the frame of the last
        self._late = 0  # frames a due trial part has waited beside the fit's new patterns
        self._begun: tuple | None = None  # a marker-space trial begun: its markers, pattern, start and frame
        self._z: np.ndarray | None = None  # the last frame's weights and pose: where the fit's warm start comes from
        # every workspace (and the IMM's spread) built now, not on the first frames
        self._fits, self._spreads = _warmed_fits(self.joint, self.profile.n_markers, self.m, self.selector.qps[0])
        self._along: dict[int, np.ndarray] = {}  # the spreads along the IMM's axes
        self._imm: RotatedIMM | None = None
        self._noise_key: tuple | None = None  # (noise, strength) the IMM's noise was last set for
        self._fit_k: int | None = None  # the strength fitted last frame
        self._fresh: FrameQP | None = None  # the fit whose next workspace was built ahead where it would not have been

    def step(self, target: np.ndarray, valid: np.ndarray) -> np.ndarray:
        if self._swap_due():
            self._swap()
        x, ok = self.filter.step(target, valid)
        if self.prior_cov is not None and self._next_check < float("inf"):
            self._stream_support(x, ok)
        self._frame += 1
        if self._begun is not None:
            self._finish()
        k = self._strength()
        fit = self._fit(k)
        if self._fit_k != k and self._z is not None:
            # a strength not fitted last frame: from the last fit, not from its own old frame (issue 39, ICT: its passes
            # 10 -> 2.5, the weights within 2e-14)
            fit.warm(self._z)
        self._fit_k = k
        # a workspace built in this step (the first frame, a new strength or prior), or one built for it last frame
        busy = not fit.knows(ok) or fit is self._fresh
        self._fresh = None
        z = self._z = fit.step(x, ok)
        # the next frame's pattern, known a frame ahead (the filter's lag): its workspace built now, on a frame
        # without a trial, so that no frame pays a trial and a new workspace, nor a new workspace and a cold solve
        ahead = self.filter.prev
        ahead = None if ahead is None or fit.knows(ahead) else ahead
        self._trial(x, ok, z, busy or ahead is not None)
        w, self.head_correction = z[:self.m], z[self.m:]
        noise = max(self.filter.noise_mm, self.calibrated_noise)
        if self._imm is None:  # the axes: the first frame's fit's; later strengths' noise is read in them
            axes = None if fit.marker_space else np.linalg.eigh(self._spread_of(k))[1]
            self._imm = RotatedIMM(axes, self.motion.imm(noise, self.norms), self.motion.shrink(), SHARED_MOVE)
            # every strength's, now: on the frame a strength first changed they cost ~30-90 µs (issue 39)
            self._along = {j: self._imm.along(self._spread_of(j)) for j in range(len(STRENGTHS))}
        if (noise, k) != self._noise_key:  # the noise settles in the first frames; the strength changes now and then
            if k not in self._along:
                self._along[k] = self._imm.along(self._spread_of(k))
            self._imm.set_noise(noise**2 * self._along[k])
            self._noise_key = (noise, k)
        # the IMM's constant-velocity models overshoot a weight resting on its limit: back within the rig's limits
        # (in place, np.clip's numbers at a third of its cost)
        out = self._imm.step(w)
        out = np.minimum(np.maximum(out, self.lower, out=out), self.upper, out=out)
        if not self._swap_due():  # (else the next frame's fit is another: it builds its workspace itself)
            self._at_leisure(fit, ahead)
        return out

    def _swap_due(self) -> bool:
        """A check's prior is due on the next frame, i.e. after ``self._frame`` frames."""
        return self._checking is not None and self._frame >= self._checking[1]

    def _strength(self) -> int:
        """The fit's strength: the held-out choice (under a prior the weakest within a standard error of the best,
        :func:`_selector`), but the grid's weakest while the prior is not yet checked against this actor (issue 41:
        docs/robustness.md, "the blink with a prior, S88-001's first seconds"; issue 41.2 measured the rule without
        this hold: S88-001 worse than no prior at 0.2 mm)."""
        return 0 if self.prior_cov is not None and self.support is None else self.selector.best

    def _at_leisure(self, fit: FrameQP, ahead: np.ndarray | None) -> None:
        """After the frame's weights: the next frame's workspace (``ahead``), also where this frame's trial changed
        the fit the next frame steps on (issue 39: those frames built it and paid ~100 µs over a known one). The
        trials come on the same frames as without these workspaces (``_fresh``)."""
        best = self._fit(self._strength())
        nxt = self.filter.prev
        if ahead is None and best is not fit:
            if not best.marker_space and nxt is not None and not best.knows(nxt):
                best.prepare(nxt)
                self._fresh = best
        elif ahead is not None:
            best.prepare(ahead)

    def _trial(self, x: np.ndarray, ok: np.ndarray, z: np.ndarray, busy: bool) -> None:
        """The held-out strength trial, due every STRENGTH_TRIAL_EVERY-th frame, never on a frame whose fit met a new
        visibility pattern (``busy``) unless it waited TRIAL_LATE_FRAMES. At rig sizes that stay in weight space the
        trial is the fit without bounds (HeldOutStrength.observe_unbounded, from this frame's fit ``z``): issue 39
        measured the bounded one on a new training pattern -- nearly every trial, with occlusion in bursts -- as
        costly as two fits, most of kalman's streamed p99 (docs/performance.md). In marker space (72 x 1000) the
        bounded trial is begun on its frame and finished before the next frame's fit (``_finish``). Its memory
        decays with the frames between trials, so the choice's half-life stays STREAM_HALF_LIFE_FRAMES."""
        if self._frame < self._due:
            return
        if busy and self._late < TRIAL_LATE_FRAMES:
            self._late += 1
            return
        self._late = 0
        if not self.selector.unbounded and self.selector.begin(x, ok, z):
            self._begun = (x.copy(), ok.copy(), z, self._frame)
        else:
            self._observe(x, ok, z)

    def _finish(self) -> None:
        """A trial begun last frame, finished before this frame's fit reads the choice: the schedule and the
        weights of a trial run whole on its frame."""
        x, ok, z, frame = self._begun
        self._begun = None
        self._observe(x, ok, z, frame)

    def _observe(self, x: np.ndarray, ok: np.ndarray, z: np.ndarray, frame: int | None = None) -> None:
        frame = self._frame if frame is None else frame  # the frame of the markers
        if self.selector.unbounded:
            self.selector.observe_unbounded(x, ok, z, elapsed=frame - self._last_trial)
        else:
            self.selector.observe(x, ok, z, elapsed=frame - self._last_trial)
        self._last_trial = frame
        self._due = frame + STRENGTH_TRIAL_EVERY

    def solve(self, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """RTS-smoothed markers -> joint pose and prior fit; POSE_PASSES times, the pose fitted on the
        smoothed markers undone on the raw ones (fitted on the raw ones it would carry their noise into
        every marker as a rigid jitter); last the IMM forwards and backwards, averaged.

        BLAS on this thread alone: every product and inverse here is of ~60 x 60 matrices, which OpenBLAS's
        other threads only slow (issue 39: the same weights bit for bit, less CPU; docs/performance.md)."""
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=1, user_api="blas"):
            return self._solve(targets, valid)

    def _solve(self, targets: np.ndarray, valid: np.ndarray) -> np.ndarray:
        valid = np.asarray(valid, bool)
        d = np.asarray(targets, float)
        self._prior_as_given()
        for i in range(POSE_PASSES):
            Z = self._solve_once(d, valid, first=i == 0)
            if i < POSE_PASSES - 1:
                d = self.pose.remove(d, valid, Z[:, self.m:])
        noise = max(self.chosen["noise_mm"], self.calibrated_noise)
        if self._product is None:
            spread = self._spread_of(int(np.argmin(np.abs(STRENGTHS - self.chosen["prior_weight"]))))
        else:
            spread = _weight_cov(self.joint[0], self._product[1], 1.0, self.m)
        axes = np.linalg.eigh(spread)[1]
        U = Z[:, :self.m] @ axes  # the fit's noise independent along these (solvers.tracking.RotatedIMM)
        r = noise**2 * variances_along(axes, spread)
        forward = self.motion.imm(noise, self.norms)
        forward.set_noise(r)
        backward = self.motion.imm(noise, self.norms)
        backward.set_noise(r)
        W = 0.5 * (forward.filter(U) + backward.filter(U[::-1])[::-1]) @ axes.T
        return np.clip(W, self.lower, self.upper)

    def _solve_once(self, targets: np.ndarray, valid: np.ndarray, first: bool = True) -> np.ndarray:
        """Weights and pose (T x (m + 6)) of the RTS-smoothed take. After the ``first`` pass, the marker noise r
        is the first's: it is the take's, and a rigid correction does not move it (issue 39: its likelihood margin
        on the ICT takes is > 1e4; the realeval rows are equal to every digit). The prior's strength by the same
        held-out markers as streamed (with an animation prior, the weaker of it and the evidence's:
        :meth:`_evidence_pick`), every strength on every frame in closed form (unbounded fits: one
        eigendecomposition per fold, solvers.prior_strength.take_strength) instead of a bounded trial QP per frame
        (issue 39 item 2: the trials were half of a 30 s take's solve; realeval's offline rows in
        docs/performance.md). With an animation prior the fit's prior is that prior times the no-prior solve's
        ridge at the ridge's own strength by its evidence (:func:`_product`): a prior from other performers was worse
        than none where it is wide along a direction the markers see weakly and its mean is off there (issue 41.2,
        alex_rom_4: the eye shapes' contrasts); the ridge holds those as the no-prior solve does (docs/robustness.md,
        "Issue 41.2: offline, a prior that cannot hurt")."""
        smoothed, ok, self.chosen = smooth_take(targets, valid, self.settings, None if first else self.chosen["r"])
        if self.prior_cov is not None and self.support is None:
            pick = _spread(len(targets), SUPPORT_TAKE_FRAMES)
            self._check_support(smoothed[pick].reshape(len(pick), -1), ok[pick], self.chosen["noise_mm"])
        B, lower, upper, mean, precision = self.joint
        if first:  # each fold's and the evidence's factors: the prior is checked by now, the second pass reuses them
            self._folds: dict = {}
            self._evidence: dict = {}
        self._product = None
        chooser = self._unwidened(precision)
        best = take_strength(B, mean, chooser, STRENGTHS, smoothed, ok, factors=self._folds)[0]
        if self.prior_cov is None:
            self.chosen["prior_weight"] = float(STRENGTHS[best])
            fit = self._fit(best)
            fit.reset()
            return fit.step_take(smoothed, ok)
        ridge = np.zeros_like(precision)
        ridge[:self.m, :self.m] = np.eye(self.m)  # the no-prior solve's (kalman_mode), at its own strength
        if first:  # by the evidence (type-II ML, MacKay 1992) of the check's frames, as the marker noise: the take's,
            # the second pass keeps it (the held-out markers' choice measured the same and cost +10 % offline)
            pick = _spread(len(smoothed), SUPPORT_TAKE_FRAMES)
            self._ridge_strength = int(np.argmax(evidence_strength(B, np.zeros_like(mean), ridge, STRENGTHS,
                                                                   smoothed[pick], ok[pick], self.m)))
        r = self._ridge_strength
        best = min(best, self._evidence_pick(B, mean, chooser, smoothed, ok))
        self.chosen["prior_weight"], self.chosen["ridge_weight"] = float(STRENGTHS[best]), float(STRENGTHS[r])
        self._product = _product(mean, STRENGTHS[best] * precision, STRENGTHS[r] * ridge, self.m)
        fit = FrameQP(B, lower, upper, prior=self._product, prior_weight=1.0)
        return fit.step_take(smoothed, ok)

    def _unwidened(self, precision: np.ndarray) -> np.ndarray:
        """``precision`` with the weights' block of the checked prior before its widening: the strength is chosen on
        it, since both criteria score the markers, which barely see the widened directions, and would otherwise
        choose a strength that undoes the widening (issue 41.2, docs/robustness.md "alex_rom_4 and its own
        performer's prior": one strength step weaker or the true spread each recovered most of its loss)."""
        s = self.support
        if s is None or not len(s.widened):
            return precision
        out = np.array(precision, float)
        out[:self.m, :self.m] = replace(s, after=s.before).precision
        return out

    def _evidence_pick(self, B: np.ndarray, mean: np.ndarray, precision: np.ndarray, smoothed: np.ndarray,
                       ok: np.ndarray) -> int:
        """An animation prior's strength by the evidence (solvers.prior_support.evidence_strength) of the check's
        frames (SUPPORT_TAKE_FRAMES, evenly spread: the evidence counts each frame as an independent draw, which
        neighbouring smoothed frames are not), which :meth:`_solve_once` takes where it is weaker than the held-out
        markers' choice. Both criteria score the markers, so neither sees the weights' error along the directions
        the markers see weakly, where this actor's mean is least known; issue 41 (docs/robustness.md, "the ICT gap
        with a prior, decomposed") measured the weight error's best strength at or below the held-out choice on all
        12 ICT takes, and the weaker of the two lowered realeval's offline means at both noises, no take worse."""
        pick = _spread(len(smoothed), SUPPORT_TAKE_FRAMES)
        return int(np.argmax(evidence_strength(B, mean, precision, STRENGTHS, smoothed[pick], ok[pick], self.m,
                                               factors=self._evidence)))


def _say(notes: list[tuple[int, str]], old: list | None = None) -> None:
    """A check's log lines; streamed, in the check's thread, which also drops the replaced fits (``old``)."""
    for level, text in notes:
        log.log(level, text)
    if old:
        old.clear()


def _selector(joint: tuple, decay: float, prior: bool) -> HeldOutStrength:
    """The streamed held-out strength choice (offline: ``take_strength``); at rig sizes whose fit stays in weight
    space (fewer shapes than MARKER_SPACE_RATIO x the marker coordinates: ICT, 72 x 150), with its trials' unbounded
    maps. Under an animation ``prior``, the weakest strength within a standard error of the best
    (solvers.prior_strength.weakest_within; issue 41.2: ICT streamed means over three noise draws 0.423 -> 0.409x at
    0.5 mm, 0.500 -> 0.491x at 0.2 mm, docs/robustness.md)."""
    B = joint[0]
    return HeldOutStrength(*joint, STRENGTHS, decay=decay, frame_passes=STREAM_PASSES,
                           unbounded=B.shape[1] < MARKER_SPACE_RATIO * B.shape[0], weakest_within=prior)


def _weight_cov(B: np.ndarray, P: np.ndarray, strength: float, m: int) -> np.ndarray:
    """The weights' covariance per unit marker variance in the fit at ``strength`` (the weights' block of the
    inverse Hessian, the head-pose columns fitted beside them marginalised)."""
    return np.linalg.inv(B.T @ B + strength * P)[:m, :m]


def _warmed_fits(joint: tuple, n_markers: int, m: int,
                 like: FrameQP | None = None) -> tuple[dict[int, FrameQP], dict[int, np.ndarray]]:
    """Every strength's fit with its all-seen workspace built (and its marker-space solver), and each one's weight
    covariance: what the first frames would otherwise build. ``like``: a QP whose B'M^2 the fits read too (the
    selector's trials': one copy in the caches for the fit and the trial)."""
    B, lower, upper, mean, precision = joint
    fits, spreads = {}, {}
    for k, a in enumerate(STRENGTHS):
        fits[k] = FrameQP(B, lower, upper, prior=(mean, precision), prior_weight=float(a), like=fits.get(0, like),
                          frame_passes=STREAM_PASSES)
        fits[k].step(np.zeros(3 * n_markers), np.ones(n_markers, bool))
        fits[k].reset()
        fits[k].prepare_marker_space()
        spreads[k] = _weight_cov(B, precision, a, m)
    return fits, spreads


def _product(mean: np.ndarray, prior: np.ndarray, ridge: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The animation prior N(mean, prior^-1) times the no-prior solve's ridge N(0, ridge^-1), each at its own strength
    (the product of two Gaussians, Bishop 2006 §2.3.3): precision prior + ridge, mean (prior + ridge)^-1 prior mean.
    Along every direction the fit is held at least as tightly as without the prior; where the markers see a direction
    weakly and the prior is wide (issue 41.2: the eye shapes' contrasts), the ridge keeps it as the no-prior solve
    would. Only the weights' block: the head-pose columns stay free."""
    precision = prior + ridge
    out = np.array(mean, float)
    out[:m] = np.linalg.solve(precision[:m, :m], prior[:m, :m] @ out[:m])
    return out, precision


def _spread(n: int, k: int) -> np.ndarray:
    """At most ``k`` indices evenly spread over ``range(n)``."""
    return np.unique(np.linspace(0, n - 1, min(n, k)).astype(int))


def kalman_prior(profile: Profile, options: Mapping | None = None) -> AnimationPrior | None:
    """The animation prior ``kalman`` fits under: option ``prior`` -- an AnimationPrior or its .npz
    (``livecap prior build``), 'profile' (the one ``calibrate --prior`` stored), 'none' (a ridge instead) --
    else the profile's. Movement's other priors ('shapes', weight curves) are refused by name."""
    spec = (options or {}).get("prior")
    if spec is None:
        return profile.prior
    spec = prior_from_spec(spec, profile.prior)
    if isinstance(spec, AnimationPrior):
        return spec
    if isinstance(spec, str) and spec == "none":
        return None
    what = "weight curves" if isinstance(spec, Mapping) else repr(spec)
    raise ValueError(f"kalman fits under an animation prior (a .npz from 'livecap prior build', 'profile' or "
                     f"'none'), not {what} (that is a movement prior)")


def kalman_mode(profile: Profile, options: Mapping | None = None) -> MarkerKalmanSolver:
    """Option ``prior`` (see :func:`kalman_prior`; without one, a ridge); ``rate`` (Hz;
    default the profile's tuned rate, else the robust modes' default) sets the IMM's per-frame process noise."""
    options = options or {}
    prior = kalman_prior(profile, options)
    if prior is None:
        mean, precision = np.zeros(len(profile.names)), np.eye(len(profile.names))
    else:
        prior.check(profile.names)
        mean, precision = prior.mean, np.linalg.inv(prior.cov)
    r = robust_settings(profile, {"rate": options.get("rate")})
    motion = WeightMotion(float(r.rate), float(r.hold_accel), float(r.move_accel), float(r.sojourn))
    settings = KalmanSettings(half_life_frames=MARKER_MEMORY_SECONDS * motion.rate)
    return MarkerKalmanSolver(profile, mean, precision, settings, motion,
                              None if prior is None else np.asarray(prior.cov, float))
