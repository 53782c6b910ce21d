"""livecap's Python API (docs/api.md): load, calibrate, solve, live, write. The commands in
``livecap.cli`` are a shell over it; ``import livecap`` exports these names lazily."""

from livecap.api.errors import ApiError
from livecap.api.live import Session, Sink
from livecap.api.load import load_layout, load_profile, load_rig, load_take
from livecap.api.solve import Solver, calibrate, settings_names, solve
from livecap.api.weights import Weights
from livecap.calibration.profile import Profile
from livecap.core.markers import MarkerLayout
from livecap.core.result import SolveResult
from livecap.core.rig import Rig
from livecap.core.take import MarkerFrame, Take

__all__ = ["ApiError", "MarkerFrame", "MarkerLayout", "Profile", "Rig", "Session", "Sink", "SolveResult", "Solver",
           "Take", "Weights", "calibrate", "load_layout", "load_profile", "load_rig", "load_take", "settings_names",
           "solve"]
