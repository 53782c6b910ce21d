"""``a2f``: the Audio2Face-3D blendshape solve (solvers.a2f_baseline) as a baseline mode, for realeval / evaluate."""

from __future__ import annotations

from collections.abc import Mapping

from livecap.calibration.profile import Profile
from solvers.a2f_baseline import A2FSolve


def a2f_mode(profile: Profile, options: Mapping | None = None) -> A2FSolve:
    """Options ``l1``, ``l2``, ``symmetry``, ``temporal``, ``sf`` (defaults: the published ones, sf 1)."""
    o = {k: float(v) for k, v in (options or {}).items() if k in ("l1", "l2", "symmetry", "temporal", "sf")}
    return A2FSolve(profile.basis, profile.lower, profile.upper, list(profile.names), **o)
