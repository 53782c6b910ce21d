"""Solver modes by name: the one place that builds a solver from a calibrated Profile.

Each family's tunables are one frozen dataclass in its module, built from the profile and the options
by one function: ``movement.MovementSettings`` (``movement_settings``), ``robust.RobustSettings``
(``robust_settings``), ``per_frame.LSQSettings`` / ``QPSettings`` / ``RBFSettings`` (``from_options``).
"""

from __future__ import annotations

from collections.abc import Callable

from livecap.calibration.profile import Profile
from livecap.modes.marker_kalman import kalman_mode
from livecap.modes.movement import build_movement
from livecap.modes.per_frame import lsq_mode, qp_mode, rbf_mode
from livecap.modes.robust import ROBUST_MODES

# The streaming mode a user gets without choosing: the most accurate one that runs per frame
# with at most a frame of latency (docs/robustness.md; `livecap evaluate` compares them all).
DEFAULT_MODE = "robust"

MODES: dict[str, Callable] = {
    "lsq": lsq_mode,
    "movement": build_movement,  # Seol 2012 movement matching; options {"stream": True, "window", "lookahead"}
    "movement-stream": lambda profile, options: build_movement(profile, {**options, "stream": True}),
    "qp": qp_mode,
    "rbf": rbf_mode,
    "kalman": kalman_mode,  # marker-space Kalman filter / RTS smoother -> bounded QP (issue 15)
}
MODES.update(ROBUST_MODES)  # noise-robust modes (livecap/modes/robust.py, docs/robustness.md)


def build_solver(mode: str, profile: Profile, options: dict | None = None):
    try:
        factory = MODES[mode]
    except KeyError:
        raise ValueError(f"unknown solver mode {mode!r} (choose from {sorted(MODES)})") from None
    return factory(profile, options or {})
