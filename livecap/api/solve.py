"""Calibrate and solve: settings in the constructor, the expensive preparation once, a cheap ``step``
per frame (the scikit-learn shape); the settings are the per-mode frozen dataclasses' fields
(livecap.modes.registry)."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np

from livecap.api.errors import ApiError
from livecap.api.weights import Weights
from livecap.calibration.animation_prior import AnimationPrior
from livecap.calibration.profile import WARPS, Profile
from livecap.core.markers import MarkerLayout
from livecap.core.result import SolveResult
from livecap.core.rig import Rig
from livecap.core.take import MarkerFrame, Take

# Options that are no field of a settings dataclass but that the factories read (``livecap solve``'s flags).
_EXTRA_SETTINGS = {"keys", "basis", "stream", "robust", "prior", "marker_weights", "temporal", "ridge"}


def settings_names() -> frozenset[str]:
    """Every name ``Solver(..., **settings)`` accepts: the fields of the per-mode settings dataclasses."""
    from livecap.modes.marker_kalman import KalmanSettings
    from livecap.modes.movement import MovementSettings
    from livecap.modes.per_frame import LSQSettings, QPSettings, RBFSettings
    from livecap.modes.robust import RobustSettings

    classes = (MovementSettings, RobustSettings, LSQSettings, QPSettings, RBFSettings, KalmanSettings)
    return frozenset(_EXTRA_SETTINGS.union(*({f.name for f in fields(c)} for c in classes)))


def calibrate(neutral_take: Take, rig: Rig, layout: MarkerLayout, *, prior: str | Path | AnimationPrior | None = None,
              seconds: float | None = None, warp: str = "rbf", smoothing: float = 0.0,
              tune_take: Take | None = None) -> Profile:
    """The actor's profile, as ``livecap calibrate`` makes it: the neutral over the first ``seconds`` of
    ``neutral_take`` (all of it when None), head motion removed, the rig's marker sites warped onto it
    (``warp``: Seol 2012 §3.2), noise and regularisation tuned on ``tune_take`` (default the neutral take),
    and an animation ``prior`` stored when given."""
    from livecap.offline.setup import calibrate_neutral, tune_on_take

    if warp not in WARPS:
        raise ApiError("warp", f"unknown warp {warp!r} (choose from {', '.join(WARPS)})")
    if seconds is not None and seconds <= 0:
        raise ApiError("seconds", f"must be > 0, got {seconds}")
    profile = calibrate_neutral(rig, layout, neutral_take, seconds=seconds, warp=warp, smoothing=smoothing,
                                prior=prior)
    tune_on_take(profile, tune_take if tune_take is not None else neutral_take)
    return profile


class Solver:
    """A calibrated solver: ``Solver(profile, mode="auto", **settings)``.

    ``mode`` is a name of ``livecap.modes.registry.MODES`` or ``"auto"`` (kalman with an animation prior,
    else robust); ``settings`` are fields of the mode's settings dataclass (``ridge=0.01``, ``trend=0``...).
    Per frame, :meth:`step` stabilises and solves one :class:`MarkerFrame` (markers in ``profile.labels``
    order); :meth:`solve_take` solves a whole take offline. ``mode_`` is the mode ``auto`` resolved to.
    """

    def __init__(self, profile: Profile, mode: str = "auto", **settings) -> None:
        from livecap.modes.registry import MODES_AND_AUTO, resolve_mode

        if not isinstance(profile, Profile):
            raise ApiError("profile", f"expected a Profile (livecap.calibrate or livecap.load_profile), "
                                      f"got {type(profile).__name__}")
        if mode not in MODES_AND_AUTO:
            raise ApiError("mode", f"unknown solver mode {mode!r} (choose from {', '.join(sorted(MODES_AND_AUTO))})")
        unknown = sorted(set(settings) - settings_names())
        if unknown:
            raise ApiError(unknown[0], f"no such solver setting (known: {', '.join(sorted(settings_names()))})")
        self.profile = profile
        self.mode = mode
        self.settings = dict(settings)
        self.mode_ = resolve_mode(mode, profile, self.settings)
        self._live = None

    def step(self, frame: MarkerFrame) -> SolveResult | None:
        """Solve one frame. None while a solver with latency L fills (its first L frames); afterwards each
        result is the frame L steps back, with that frame's number, time and head pose."""
        if self._live is None:
            from livecap.live.pipeline import Pipeline

            self._live = Pipeline([], [], profile=self.profile, mode=self.mode, options=self.settings)
        if len(frame.positions) != self.profile.n_markers:
            raise ApiError("frame", f"{len(frame.positions)} markers, the profile has {self.profile.n_markers} "
                                    "(give them in profile.labels order: Take.select(profile.labels))")
        return self._live.solve_frame(frame)

    def reset(self) -> None:
        """Forget the frames seen by :meth:`step` (a new take starts)."""
        self._live = None

    def solve_take(self, take: Take) -> Weights:
        """Every frame of ``take`` solved offline, as ``livecap solve`` does (whole-take modes see the take)."""
        from livecap.batch.stats import frame_residual
        from livecap.modes.registry import build_solver
        from livecap.offline.setup import check_labels
        from livecap.offline.solve import solve_take

        if not isinstance(take, Take):
            raise ApiError("take", f"expected a Take (livecap.load_take), got {type(take).__name__}")
        check_labels(take, self.profile.labels, "take", "profile")
        solved = solve_take(take, self.profile, build_solver(self.mode_, self.profile, self.settings))
        n = len(solved.weights)
        return Weights(solved.names, np.arange(n) / solved.rate, solved.weights, solved.head_rotation,
                       solved.head_translation, frame_residual(solved, self.profile), solved.rate, solved.first_frame)


def solve(take_path: str | Path, *, rig: str | Path, profile: str | Path | Profile | None = None,
          mode: str = "auto", markers: str | Path | None = None, neutral_seconds: float = 1.0,
          **settings) -> Weights:
    """``livecap solve`` in one call: the take at ``take_path`` solved for the rig at ``rig``, with
    ``profile`` (a path or a Profile), else one calibrated on the take's first ``neutral_seconds``."""
    from livecap.api.load import _existing, load_layout, load_profile, load_rig, load_take
    from livecap.offline.setup import check_labels, check_profile_for_rig, profile_from_take

    take = load_take(take_path)
    if profile is None:
        if neutral_seconds <= 0:
            raise ApiError("neutral_seconds", f"must be > 0, got {neutral_seconds}")
        rig_ = load_rig(rig)
        layout = load_layout(rig, rig_, markers=markers)
        check_labels(take, layout.labels, take_path, rig)
        profile = profile_from_take(rig_, layout, take, neutral_seconds)
    else:
        where = "profile" if isinstance(profile, Profile) else profile
        if not isinstance(profile, Profile):
            profile = load_profile(profile)
        try:
            check_profile_for_rig(profile, _existing("rig", rig), where, markers)
        except ValueError as exc:  # another rig's profile, or markers bound elsewhere, would solve silently badly
            raise ApiError("profile", str(exc)) from None
    return Solver(profile, mode, **settings).solve_take(take)
