"""The streamed strength under an animation prior: the weakest within a standard error of the best (issue 41.2)."""

import numpy as np
import pytest

from solvers.prior_strength import weakest_within


def test_flat_scores_give_the_weakest_and_a_clear_minimum_keeps_the_best():
    count = np.full(5, 60.0)  # relative standard error sqrt(2 / 180) = 0.105
    flat = np.array([1.05, 1.02, 1.0, 1.01, 1.3]) * count
    assert weakest_within(flat, count, 2) == 0
    clear = np.array([1.5, 1.2, 1.0, 1.01, 1.3]) * count
    assert weakest_within(clear, count, 2) == 2


@pytest.mark.parametrize("n", [10.0, 100.0, 10_000.0])
def test_the_margin_is_the_noise_models_standard_error(n):
    """Just inside one standard error of the best counts as a tie, just outside does not; more held-out markers, a
    narrower margin."""
    se = np.sqrt(2.0 / (3.0 * n))
    count = np.full(3, n)
    assert weakest_within(np.array([1.0 + 0.99 * se, 1.0, 1.2]) * count, count, 1) == 0
    assert weakest_within(np.array([1.0 + 1.01 * se, 1.0, 1.2]) * count, count, 1) == 1


def test_streamed_kalman_with_a_prior_takes_the_weakest_within_and_a_ridge_the_best():
    """Under an animation prior the streamed choice is :func:`weakest_within` of the trials' scores, on this take
    weaker than their least-error strength on some frames (the test sees the rule act); a ridge keeps the least-error
    strength (its mean is no performer's)."""
    from livecap.modes.marker_kalman import kalman_mode
    from tests.test_prior_support import _tight_prior_take

    p, _, X = _tight_prior_take(T=240)
    weaker = 0
    for prior in (True, False):
        if not prior:
            p.prior = None
        solver = kalman_mode(p, {"rate": 60.0})
        assert solver.selector.weakest_within is prior
        for t in range(len(X)):
            solver.step(X[t], np.ones(40, bool))
            s = solver.selector
            if not s._counted:
                continue
            least = int(np.argmin(s.err / s.count))
            if prior:
                assert s.best == weakest_within(s.err, s.count, least) <= least
                weaker += s.best < least
            else:
                assert s.best == least
    assert weaker > 0


def test_a_strength_never_scored_is_not_chosen_by_the_rule():
    count = np.array([0.0, 5.0, 5.0])
    err = np.array([0.0, 5.0, 4.9])  # strength 0 never scored (0 / 0)
    assert weakest_within(err, count, 2) == 1
    assert weakest_within(err, count, 0) == 0  # the kernel's own choice, kept
