"""Direct manipulation (Lewis & Anjyo 2010): bounded pin solve against scipy's bounded least squares."""

import numpy as np
import pytest
import scipy.optimize
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.manipulation import DirectManipulation, ManipulationSettings


def _problem(seed: int, m: int = 12, pins: int = 3):
    rng = np.random.default_rng(seed)
    deltas = rng.normal(size=(m, pins, 3)) * 5.0
    rest = rng.normal(size=(pins, 3)) * 20.0
    current = rng.uniform(0, 1, m)
    goals = rest + np.einsum("m,mpk->pk", rng.uniform(-0.5, 1.5, m), deltas)
    return rest, deltas, current, goals


def _reference(rest, deltas, current, goals, pull, lo, hi):
    m = deltas.shape[0]
    A = np.vstack([deltas.reshape(m, -1).T, np.sqrt(pull) * np.eye(m)])
    b = np.concatenate([(goals - rest).ravel(), np.sqrt(pull) * current])
    return scipy.optimize.lsq_linear(A, b, bounds=(lo, hi), tol=1e-12, method="bvls").x


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), pull=st.floats(0.01, 100.0), pins=st.integers(1, 6))
def test_matches_bounded_least_squares_and_stays_in_limits(seed, pull, pins):
    rest, deltas, current, goals = _problem(seed, pins=pins)
    m = deltas.shape[0]
    lo, hi = np.zeros(m), np.ones(m)
    dm = DirectManipulation(rest, deltas, lo, hi, ManipulationSettings(pull=pull))
    w = dm.step(goals, current)
    assert np.all(w >= lo) and np.all(w <= hi)
    ref = _reference(rest, deltas, current, goals, pull, lo, hi)
    assert dm.objective(w, goals, current) <= dm.objective(ref, goals, current) + 1e-7 * (1 + abs(
        dm.objective(ref, goals, current)))
    np.testing.assert_allclose(w, ref, atol=1e-6)


def test_goals_at_the_current_pose_keep_the_weights():
    rest, deltas, current, _ = _problem(3)
    dm = DirectManipulation(rest, deltas, 0.0, 1.0)
    goals = rest + np.einsum("m,mpk->pk", current, deltas)
    np.testing.assert_allclose(dm.step(goals, current), current, atol=1e-9)


def test_reachable_pin_is_reached_when_the_pull_is_small():
    rest, deltas, _, _ = _problem(5, m=12, pins=2)
    target_w = np.linspace(0.1, 0.9, 12)
    goals = rest + np.einsum("m,mpk->pk", target_w, deltas)
    dm = DirectManipulation(rest, deltas, 0.0, 1.0, ManipulationSettings(pull=1e-6))
    w = dm.step(goals, np.zeros(12))
    reached = rest + np.einsum("m,mpk->pk", w, deltas)
    assert np.max(np.abs(reached - goals)) < 1e-3


def test_bad_pull_is_refused():
    rest, deltas, _, _ = _problem(1)
    with pytest.raises(ValueError, match="pull"):
        DirectManipulation(rest, deltas, 0.0, 1.0, ManipulationSettings(pull=0.0))
