"""Issue 41.3: `--mode movement --prior profile` uses the prior (it was byte-identical to no prior) and a profile's
stored prior is movement's default, as for kalman."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from livecap.calibration.animation_prior import AnimationPrior
from livecap.calibration.profile import Profile
from livecap.modes.movement import movement_settings
from livecap.modes.registry import build_solver
from livecap.offline.solve import solve_take
from transport.takefile import read_take

REC = Path(__file__).resolve().parents[1] / "recordings"


@pytest.fixture(scope="module")
def profile(demo_profile_path):
    p = Profile.load(demo_profile_path)
    m = len(p.names)
    rng = np.random.default_rng(0)
    A = rng.normal(size=(m, m)) * 0.05
    p.prior = AnimationPrior(tuple(p.names), np.full(m, 0.1), A @ A.T + 1e-3 * np.eye(m), 1000, ("test",))
    return p


def test_movement_uses_the_prior_it_is_given(profile):
    take = read_take(REC / "demo_take.c3d").slice(0, 200)
    W = {spec: solve_take(take, profile, build_solver("movement", profile, {"prior": spec})).weights
         for spec in ("profile", "none")}
    assert np.abs(W["profile"] - W["none"]).max() > 1e-3
    default = solve_take(take, profile, build_solver("movement", profile)).weights
    np.testing.assert_array_equal(default, W["profile"])


def test_the_prior_weight_follows_the_noise(profile):
    """alpha = the smoothed velocity residual's variance: 4x for twice the noise, 0 without an animation prior."""
    s = movement_settings(profile)
    noisier = replace(profile, settings={**profile.settings, "robust": {**profile.settings["robust"],
                                         "noise_mm": 2 * profile.settings["robust"]["noise_mm"]}})
    assert s.alpha > 0 and movement_settings(noisier).alpha == pytest.approx(4 * s.alpha)
    assert movement_settings(profile, {"prior": "none"}).alpha == 0.0
    assert movement_settings(profile, {"prior": "shapes"}).alpha == 0.0
