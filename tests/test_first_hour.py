"""Issue 21, a user's first hour: each finding's fix, checked the way the user met it."""

import logging
from pathlib import Path

import pytest

from livecap.calibration.profile import Profile
from livecap.cli import main
from livecap.modes.registry import build_solver
from livecap.modes.robust_movement import RobustMovement

REC = Path(__file__).resolve().parents[1] / "recordings"
RIG = str(REC / "demo_rig.npz")


@pytest.fixture(scope="module")
def plain_profile(tmp_path_factory):
    """The profile docs/calibration.md's first command writes: ``calibrate`` with no --tune."""
    out = tmp_path_factory.mktemp("cal") / "actor.npz"
    assert main(["calibrate", str(REC / "demo_neutral.c3d"), "--rig", RIG, "--out", str(out)]) == 0
    return Profile.load(out)


def test_plain_calibrate_stores_the_noise_estimate(plain_profile):
    """Finding 1: the plain profile carries the noise estimate, so movement is the noise-robust solve."""
    noise = plain_profile.settings["robust"]["noise_mm"]
    assert 0.4 < noise < 0.6  # the demo's markers carry 0.5 mm noise
    assert isinstance(build_solver("movement", plain_profile), RobustMovement)


def test_a_mode_that_falls_back_says_so_once(plain_profile, caplog):
    old = Profile(**{**vars(plain_profile), "settings": {k: v for k, v in plain_profile.settings.items()
                                                          if k != "robust"}})
    for mode in ("movement", "robust"):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            build_solver(mode, old)
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1 and "no noise estimate" in warnings[0].getMessage()
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        build_solver("movement", old, {"robust": False})  # --plain asked for it: nothing to say
        build_solver("movement", plain_profile)
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]
