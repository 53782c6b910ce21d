"""Solver modes by name: the one place that builds a solver from a calibrated Profile.

Each family's tunables are one frozen dataclass in its module, built from the profile and the options
by one function: ``movement.MovementSettings`` (``movement_settings``), ``robust.RobustSettings``
(``robust_settings``), ``per_frame.LSQSettings`` / ``QPSettings`` / ``RBFSettings`` (``from_options``).
"""

from __future__ import annotations

from collections.abc import Callable

from livecap.calibration.profile import Profile
from livecap.modes.a2f import a2f_mode
from livecap.modes.marker_kalman import kalman_mode, kalman_prior
from livecap.modes.movement import build_movement
from livecap.modes.per_frame import lsq_mode, qp_mode, rbf_mode
from livecap.modes.quiet import build_quiet
from livecap.modes.robust import ROBUST_MODES

# The mode a user gets without choosing (docs/modes.md "The default mode"; measured leave one file out
# on real performances in docs/robustness.md): ``kalman`` -- a dense fit under a Gaussian prior, or a ridge
# without one -- unless the take calibration tuned on shows sparse acting (few shapes at a time, as the bundled
# demo take's script: livecap.modes.robust.acting_density), where ``robust`` -- the sparse L1 fit -- wins. Both
# run per frame with at most one frame of latency and have an offline form.
DEFAULT_MODE = "auto"
DENSE_MAX_SHAPES = 200  # without a prior, rigs with more shapes keep robust: kalman's per-frame cost grows too fast

MODES: dict[str, Callable] = {
    "lsq": lsq_mode,
    "movement": build_movement,  # Seol 2012 movement matching; options {"stream": True, "window", "lookahead"}
    "movement-stream": lambda profile, options: build_movement(profile, {**options, "stream": True}),
    "qp": qp_mode,
    "rbf": rbf_mode,
    "kalman": kalman_mode,  # marker-space Kalman filter / RTS smoother -> bounded QP (issue 15)
    "a2f": a2f_mode,  # baseline: NVIDIA Audio2Face-3D's published blendshape solve (issue 41.7)
}
MODES.update(ROBUST_MODES)  # noise-robust modes (livecap/modes/robust.py, docs/robustness.md)
MODES_AND_AUTO = [DEFAULT_MODE, *MODES]  # what --mode accepts
MODE_HELP = (f"solver mode (default {DEFAULT_MODE}: kalman, or robust when no animation prior is given and the take "
             "calibration tuned on shows sparse acting)")


def resolve_mode(mode: str, profile: Profile, options: dict | None = None) -> str:
    """The mode ``auto`` stands for with this profile and options; any other name unchanged."""
    if mode != DEFAULT_MODE:
        return mode
    if kalman_prior(profile, options) is not None:
        return "kalman"
    tuned = profile.settings.get("robust", {})
    if "noise_mm" not in tuned:  # a profile written before calibration tuned (nothing measured): as it was then
        return "robust"
    if len(profile.names) > DENSE_MAX_SHAPES:  # kalman cannot stream there (docs/modes.md: 94 / 343 ms at 1000)
        return "robust"
    return "robust" if tuned.get("acting") == "sparse" else "kalman"


def build_solver(mode: str, profile: Profile, options: dict | None = None):
    mode = resolve_mode(mode, profile, options)
    try:
        factory = MODES[mode]
    except KeyError:
        raise ValueError(f"unknown solver mode {mode!r} (choose from {sorted(MODES_AND_AUTO)})") from None
    options = options or {}
    return build_quiet(factory, profile, options, reduce=mode != "rbf" and options.get("basis") != "actor")
