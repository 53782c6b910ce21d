"""kalman's streamed held-out strength trial kept off the frames that pay for anything else (issue 39)."""

from __future__ import annotations

import numpy as np

from solvers.prior_strength import HeldOutStrength
from solvers.qp import FrameQP
from tests.test_marker_kalman import _face


def _problem(seed: int = 0, n: int = 12, m: int = 5):
    rng = np.random.default_rng(seed)
    B = rng.normal(0, 1, (3 * n, m))
    return B, rng, n, m


def test_a_prepared_pattern_is_known_and_solves_as_an_unprepared_one():
    B, rng, n, m = _problem()
    seen = np.ones(n, bool)
    seen[[2, 7]] = False
    target = B @ rng.uniform(0, 1, m) + rng.normal(0, 0.01, 3 * n)
    prepared, plain = (FrameQP(B, np.zeros(m), np.ones(m), ridge=0.1) for _ in range(2))
    assert not prepared.knows(seen)
    prepared.prepare(seen)
    assert prepared.knows(seen) and prepared.cached_patterns == 1
    np.testing.assert_allclose(prepared.step(target, seen), plain.step(target, seen), atol=1e-12)
    assert prepared.cached_patterns == 1  # the step built nothing more


def test_a_trial_split_over_two_frames_scores_as_one_and_its_memory_follows_the_frames():
    B, rng, n, m = _problem(1)
    args = (B, np.zeros(m), np.ones(m), np.full(m, 0.5), np.eye(m), np.logspace(-2, 1, 4))
    split, whole = (HeldOutStrength(*args, decay=0.9) for _ in range(2))
    stepped = HeldOutStrength(*args, decay=0.9 ** 3)  # a trial every frame, its decay three frames'
    for _ in range(30):
        valid = rng.uniform(size=n) > 0.2
        target = B @ rng.uniform(0, 1, m) + rng.normal(0, 0.05, 3 * n)
        if split.prepare(valid):
            assert not split.prepare(valid)  # built: the trial now finds it
        split.observe(target, valid, elapsed=3)
        whole.observe(target, valid, elapsed=3)
        stepped.observe(target, valid)
    np.testing.assert_allclose(split.err, whole.err, rtol=1e-12)
    np.testing.assert_allclose(whole.err, stepped.err, rtol=1e-12)
    assert split.best == whole.best == stepped.best


def test_no_streamed_frame_both_builds_a_trial_workspace_and_solves_a_trial():
    """Occlusion in bursts: most trial patterns are new. The code before built the trial's workspace and solved it
    on the same frame, every 2nd frame; now a build and a solve fall on different frames, at nearly the same rate."""
    from livecap.modes import marker_kalman as mk

    p = _face()
    rng = np.random.default_rng(4)
    T, n = 360, p.n_markers
    W = np.clip(0.4 + 0.2 * np.sin(np.arange(T)[:, None] / rng.uniform(5, 30, p.basis.shape[1])), 0, 1)
    X = (W @ p.basis.T).reshape(T, n, 3) + rng.normal(0, 0.3, (T, n, 3))
    valid = np.ones((T, n), bool)
    for start in rng.integers(0, T, 60):  # 60 bursts of 5-20 frames, one marker each
        valid[start:start + rng.integers(5, 20), rng.integers(6, n)] = False
    solver = mk.kalman_mode(p, {"rate": 60.0})
    events: list[set] = [set() for _ in range(T)]
    frame = [0]
    for qp in solver.selector.qps:
        def workspace(key, seen, qp=qp, inner=qp._workspace):
            if key not in qp._models:
                events[frame[0]].add("build")
            return inner(key, seen)

        def step(target, ok, inner=qp.step):
            events[frame[0]].add("solve")
            return inner(target, ok)

        qp._workspace, qp.step = workspace, step
    for t in range(T):
        frame[0] = t
        solver.step(X[t], valid[t])
    both = [t for t in range(T) if events[t] == {"build", "solve"}]
    assert not both, f"frames {both[:5]} build a trial's workspace and solve a trial"
    trials = sum("solve" in e for e in events)
    assert trials >= T // (mk.STRENGTH_TRIAL_EVERY + 1)  # one every 2nd frame, every 3rd on a new pattern
    assert sum("build" in e for e in events) > 0  # the bursts did make new trial patterns


def test_a_marker_space_trial_begun_on_its_frame_scores_as_one():
    """At many shapes (the marker-space path: 8 markers, 80 shapes and a pose) a known pattern's trial is begun
    on the frame it is due (its first passes) and finished on the next, with the score of a whole trial."""
    from tests.test_marker_space_qp import _rig

    (B, lo, hi, mean, P), rng = _rig(8, 80)
    args = (B, lo, hi, mean, P, np.array([1e-2, 1e-1]))
    split, whole = (HeldOutStrength(*args, folds=4) for _ in range(2))
    begun = 0
    w_true = rng.uniform(0.2, 0.6, 80)
    for _ in range(24):
        w_true = np.clip(w_true + rng.normal(0, 0.05, 80), 0.0, 1.0)
        target = B[:, :80] @ w_true + rng.normal(0, 0.3, 24)
        valid = np.ones(8, bool)
        start = np.r_[w_true, np.zeros(6)]
        begun += split.begin(target, valid, start)
        split.observe(target, valid, start)
        whole.observe(target, valid, start)
    assert begun > 12
    np.testing.assert_array_equal(split.err, whole.err)
