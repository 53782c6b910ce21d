"""Issue 35.3: shapes the markers cannot see stay quiet in every mode, at rest or at the prior's conditional mean."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from livecap.calibration.animation_prior import AnimationPrior
from livecap.calibration.profile import Profile
from livecap.modes.registry import build_solver
from livecap.modes.robust import override_noise
from livecap.offline.solve import solve_take
from solvers.observability import quiet_shapes
from transport.takefile import read_take

REC = Path(__file__).resolve().parents[1] / "recordings"


@pytest.fixture(scope="module")
def noisy_profile(demo_profile_path):
    """The demo actor, its markers trusted at 2 mm (as a capture whose rig misses the face by that much)."""
    p = Profile.load(demo_profile_path)
    override_noise(p, 2.0)
    return p


@pytest.fixture(scope="module")
def take():
    return read_take(REC / "demo_take.c3d").slice(0, 240)


def test_the_cone_keeps_opposite_shapes_and_drops_a_near_duplicate():
    rng = np.random.default_rng(1)
    b = rng.normal(size=(30, 3))
    dup = b[:, 0] + 0.01 * rng.normal(size=30)
    B = np.column_stack([b, -b[:, 2], dup])  # shape 3 = -shape 2 (jawLeft / jawRight); shape 4 ~ shape 0
    assert quiet_shapes(B, 0.5).tolist() in ([0], [4])
    assert quiet_shapes(B, 1e-6).tolist() == []


@pytest.mark.parametrize("mode", ["lsq", "qp", "robust", "kalman", "movement"])
def test_held_shapes_stay_at_rest_in_every_mode(noisy_profile, take, mode):
    held = quiet_shapes(noisy_profile.basis, 2.0)
    assert len(held) >= 3
    W = solve_take(take, noisy_profile, build_solver(mode, noisy_profile)).weights
    assert W.shape[1] == len(noisy_profile.names) and np.all(W[:, held] == 0.0)
    if mode != "robust":  # robust's L1 threshold at 2 mm keeps these at 0 here anyway
        loose = solve_take(take, noisy_profile, build_solver(mode, noisy_profile, {"quiet": False})).weights
        assert np.abs(loose[:, held]).max() > 0.01  # without it, they move


def test_with_a_prior_held_shapes_follow_its_conditional_mean(noisy_profile, take):
    m = len(noisy_profile.names)
    rng = np.random.default_rng(0)
    A = rng.normal(size=(m, m)) * 0.05
    prior = AnimationPrior(tuple(noisy_profile.names), np.full(m, 0.2), A @ A.T + 1e-2 * np.eye(m), 100, ("t",))
    p = replace(noisy_profile, prior=prior)
    held = quiet_shapes(p.basis, 2.0)
    keep = np.setdiff1d(np.arange(m), held)
    solver = build_solver("kalman", p)
    W = solve_take(take, p, solver).weights
    S = prior.cov
    expect = prior.mean[held] + (W[:, keep] - prior.mean[keep]) @ np.linalg.solve(S[np.ix_(keep, keep)],
                                                                                   S[np.ix_(keep, held)])
    np.testing.assert_allclose(W[:, held], np.clip(expect, p.lower[held], p.upper[held]), atol=1e-9)
    st = build_solver("kalman", p)
    w = st.step(np.zeros((len(p.labels), 3)), np.ones(len(p.labels), bool))
    assert w.shape == (m,)


def test_info_observability_names_the_held_shapes(noisy_profile):
    from solvers.observability import observability

    rep = observability(noisy_profile.basis, noisy_profile.names, 2.0)
    names = [noisy_profile.names[i] for i in quiet_shapes(noisy_profile.basis, 2.0)]
    assert rep.lines()[-1].endswith(", ".join(names)) and names
