"""Each mode family's tunables: one frozen dataclass, resolved in one function (issue 23)."""

import dataclasses

import numpy as np
import pytest

from livecap.calibration.profile import Profile, calibrate
from livecap.modes.movement import MovementSettings, movement_settings
from livecap.modes.per_frame import QPSettings, RBFSettings
from livecap.modes.registry import build_solver
from livecap.modes.robust import RobustSettings, robust_settings
from livecap.modes.robust_movement import RobustMovement


@pytest.fixture(scope="module")
def profile(demo):
    rig, layout = demo
    return calibrate(rig, layout, layout.marker_rig(rig).neutral)  # the rig's own proportions


def test_settings_are_frozen_with_documented_defaults():
    for cls in (RobustSettings, MovementSettings, QPSettings, RBFSettings):
        s = cls()
        field = dataclasses.fields(cls)[0]
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(s, field.name, 1)


def test_robust_settings_order_defaults_profile_options(profile):
    p = Profile(**{**vars(profile), "settings": {"robust": {"noise_mm": 0.3, "sparse_ridge": 0.2, "rate": 60.0,
                                                             "criterion": "held-out markers"}}})
    assert robust_settings(profile) == RobustSettings()
    s = robust_settings(p, {"lag": 2, "trend": None, "keys": "ignored.json"})
    assert (s.noise_mm, s.sparse_ridge, s.rate, s.lag, s.trend) == (0.3, 0.2, 60.0, 2, RobustSettings.trend)
    assert robust_settings(p, {"ridge": 3.0}).sparse_ridge == 3.0  # --ridge sets both fits' ridges


def test_profiles_saved_before_still_load(profile, tmp_path):
    """A profile written with the old keys (the 1€ 'beta', the deleted 'tie') loads and builds every robust mode."""
    old = Profile(**{**vars(profile), "settings": {"robust": {"noise_mm": 0.4, "beta": 12.0, "tie": 0.0,
                                                               "ridge": 2.0, "ridge_gcv": 3.0}}})
    old.save(tmp_path / "old.npz")
    loaded = Profile.load(tmp_path / "old.npz")
    s = robust_settings(loaded)
    assert s.euro_beta == 12.0 and s.noise_mm == 0.4 and s.prior_ridge == 2.0
    for mode in ("robust", "robust-lag", "movement"):
        assert build_solver(mode, loaded) is not None


def test_movement_defaults_follow_the_profile(profile):
    plain = movement_settings(profile)
    assert plain == MovementSettings() and not plain.robust
    tuned = Profile(**{**vars(profile), "settings": {"robust": {"noise_mm": 0.5}}})
    s = movement_settings(tuned)
    assert s.robust and s.alpha == 0.0 and s.limits == "bound" and s.beta != MovementSettings.beta
    assert movement_settings(tuned, {"beta": 0.7}).beta == 0.7
    assert not movement_settings(tuned, {"robust": False}).robust
    assert not movement_settings(tuned, {"stream": True}).robust
    assert isinstance(build_solver("movement", tuned), RobustMovement)


def test_per_frame_settings_ignore_unset_options():
    assert QPSettings.from_options({"ridge": None, "temporal": 2.0, "alpha": 1.0}) == QPSettings(temporal=2.0)
    assert RBFSettings.from_options({"clip": False}).clip is False
    assert np.isclose(QPSettings().ridge, 0.0)
