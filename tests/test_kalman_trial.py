"""kalman's streamed held-out strength trial kept off the frames that pay for anything else (issue 39)."""

from __future__ import annotations

import numpy as np
import pytest

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


def test_no_streamed_frame_both_builds_a_trial_workspace_and_solves_a_trial_nor_carries_one_beside_a_new_fit():
    """Occlusion in bursts: most trial patterns are new. The code before built the trial's workspace and solved it
    on the same frame, every 2nd frame; now a build and a solve fall on different frames, at nearly the same rate,
    and no trial part falls on a frame whose fit met a new visibility pattern unless it waited TRIAL_LATE_FRAMES
    (issue 39: the code before put a trial part on ~40 % of those frames)."""
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

    def watch(qp, build, solve):
        def workspace(key, seen, inner=qp._workspace):
            if key not in qp._models:
                events[frame[0]].add(build)
            return inner(key, seen)

        def step(target, ok, inner=qp.step):
            events[frame[0]].add(solve)
            return inner(target, ok)

        qp._workspace, qp.step = workspace, step

    for qp in solver.selector.qps:
        watch(qp, "build", "solve")
    for qp in solver._fits.values():
        watch(qp, "new fit pattern", "fit")
    for t in range(T):
        frame[0] = t
        solver.step(X[t], valid[t])
    both = [t for t in range(T) if {"build", "solve"} <= events[t]]
    assert not both, f"frames {both[:5]} build a trial's workspace and solve a trial"
    trials = sum("solve" in e for e in events)
    assert trials >= 0.9 * T // (mk.STRENGTH_TRIAL_EVERY + 1)  # one every 2nd frame, every 3rd on a new pattern
    assert sum("build" in e for e in events) > 0  # the bursts did make new trial patterns
    new_fit = [t for t in range(T) if "new fit pattern" in events[t]]
    assert len(new_fit) > 20
    beside = [t for t in new_fit if events[t] & {"build", "solve"}]
    # a trial part beside a new fit pattern only after TRIAL_LATE_FRAMES frames of new patterns before it
    assert all(all("new fit pattern" in events[t - d] for d in range(1, mk.TRIAL_LATE_FRAMES + 1)) for t in beside)


def test_the_compiled_held_out_error_is_the_numpy_sum_it_replaced():
    from solvers.prior_strength_kernels import held_out_error

    rng = np.random.default_rng(7)
    n, m = 15, 8
    B, w, s = rng.normal(0, 2, (3 * n, m)), rng.normal(0, 1, m), rng.normal(0, 5, 3 * n)
    markers = np.array([1, 4, 6, 11, 14])
    for seen in (np.ones(5, bool), np.array([True, False, True, True, False]), np.zeros(5, bool)):
        rows = np.repeat(3 * markers[seen], 3) + np.tile(np.arange(3), int(seen.sum()))
        r = B[rows] @ w - s[rows]
        assert held_out_error(B, markers, seen, w, s) == pytest.approx(float(r @ r), rel=1e-13, abs=1e-300)
