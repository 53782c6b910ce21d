"""kalman's streamed held-out strength trial: cheap, and kept off the frames that pay for anything else (issue 39)."""

from __future__ import annotations

import numpy as np
import pytest

from solvers.prior_strength import HeldOutStrength
from tests.test_marker_kalman import _face


def _bursty_take(p, seed: int, T: int, amplitude: float, fastest: float, noise_mm: float):
    """Slow sines about 0.4 with occlusion in bursts: 60 bursts of 5-20 frames, one marker each (not the first 6)."""
    rng = np.random.default_rng(seed)
    n = p.n_markers
    W = np.clip(0.4 + amplitude * np.sin(np.arange(T)[:, None] / rng.uniform(fastest, 30, p.basis.shape[1])), 0, 1)
    X = (W @ p.basis.T).reshape(T, n, 3) + rng.normal(0, noise_mm, (T, n, 3))
    valid = np.ones((T, n), bool)
    for start in rng.integers(0, T, 60):
        valid[start:start + rng.integers(5, 20), rng.integers(6, n)] = False
    return X, valid


def _problem(seed: int = 0, n: int = 12, m: int = 5):
    rng = np.random.default_rng(seed)
    B = rng.normal(0, 1, (3 * n, m))
    return B, rng, n, m


def test_a_trials_memory_follows_the_frames():
    B, rng, n, m = _problem(1)
    args = (B, np.zeros(m), np.ones(m), np.full(m, 0.5), np.eye(m), np.logspace(-2, 1, 4))
    every_third = HeldOutStrength(*args, decay=0.9)
    stepped = HeldOutStrength(*args, decay=0.9 ** 3)  # a trial every frame, its decay three frames'
    for _ in range(30):
        valid = rng.uniform(size=n) > 0.2
        target = B @ rng.uniform(0, 1, m) + rng.normal(0, 0.05, 3 * n)
        every_third.observe(target, valid, elapsed=3)
        stepped.observe(target, valid)
    np.testing.assert_allclose(every_third.err, stepped.err, rtol=1e-12)
    assert every_third.best == stepped.best


def test_an_unbounded_trial_is_the_bounded_one_where_no_bound_binds_and_fills_hidden_markers_from_the_fit():
    """observe_unbounded (kalman's streamed trial, issue 39): the fit on every marker outside the fold, without
    bounds, clipped; markers the frame misses take the fit's prediction B fill."""
    B, rng, n, m = _problem(2, n=15, m=6)
    lo, hi, mu, P = np.full(m, -1e3), np.full(m, 1e3), rng.uniform(0, 1, m), np.eye(m) + 0.3
    grid = np.logspace(-2, 1, 3)
    bounded = HeldOutStrength(B, lo, hi, mu, P, grid)
    fast = HeldOutStrength(B, lo, hi, mu, P, grid, unbounded=True)
    for _ in range(2 * len(grid) * 5):
        target = B @ rng.uniform(0, 1, m) + rng.normal(0, 0.05, 3 * n)
        bounded.observe(target, np.ones(n, bool))
        fast.observe_unbounded(target, np.ones(n, bool), np.zeros(m))
    np.testing.assert_allclose(fast.err, bounded.err, rtol=1e-8)
    # hidden markers outside the fold: their rows from the fill, the result clipped
    lo, hi = np.zeros(m), np.full(m, 0.6)
    sel = HeldOutStrength(B, lo, hi, mu, P, grid, unbounded=True)
    valid = np.ones(n, bool)
    f = 0  # the first trial's fold (and strength 0)
    out = np.flatnonzero(sel.fold_of != f)
    valid[out[:2]] = False
    valid[np.flatnonzero(sel.fold_of == f)[0]] = False  # a held-out marker missing: not scored
    target, fill = B @ rng.uniform(0, 1, m) + rng.normal(0, 0.05, 3 * n), rng.uniform(0, 1, m)
    rows = np.flatnonzero(np.repeat(sel.fold_of != f, 3))
    x = np.where(np.repeat(valid, 3), target, B @ fill)[rows]
    w = np.clip(np.linalg.solve(B[rows].T @ B[rows] + grid[0] * P, B[rows].T @ x + grid[0] * P @ mu), lo, hi)
    held = np.repeat((sel.fold_of == f) & valid, 3)
    sel.observe_unbounded(target, valid, fill)
    assert sel.err[0] == pytest.approx(float(np.sum((B[held] @ w - target[held]) ** 2)), rel=1e-10)
    assert sel.count[0] == np.count_nonzero((sel.fold_of == f) & valid)


def test_streamed_trials_solve_no_qp_and_none_falls_beside_a_new_fit_pattern():
    """Occlusion in bursts: nearly every bounded trial's training pattern was new to its QP (a workspace and a cold
    factor each). Streamed, the trials are unbounded: no trial QP is stepped; a trial comes every 2nd frame, and
    never on a frame whose fit met a new visibility pattern unless it waited TRIAL_LATE_FRAMES (issue 39: the code
    before put a trial part on ~40 % of those frames)."""
    from livecap.modes import marker_kalman as mk

    p = _face()
    T = 360
    X, valid = _bursty_take(p, 4, T, 0.2, 5, 0.3)
    solver = mk.kalman_mode(p, {"rate": 60.0})
    assert solver.selector.unbounded
    events: list[set] = [set() for _ in range(T)]
    frame = [0]

    def watch(obj, name, event):
        inner = getattr(obj, name)

        def call(*a, **k):
            events[frame[0]].add(event)
            return inner(*a, **k)

        setattr(obj, name, call)

    for qp in solver.selector.qps:
        watch(qp, "step", "trial QP")
    watch(solver.selector, "observe_unbounded", "trial")
    for qp in solver._fits.values():
        def workspace(key, seen, qp=qp, inner=qp._workspace):
            if key not in qp._models:
                events[frame[0]].add("new fit pattern")
            return inner(key, seen)

        qp._workspace = workspace
    changed = []
    for t in range(T):
        frame[0] = t
        best = solver.selector.best
        solver.step(X[t], valid[t])
        if solver.selector.best != best:
            changed.append(t)
    assert not any("trial QP" in e for e in events)
    trials = sum("trial" in e for e in events)
    assert trials >= 0.8 * T / mk.STRENGTH_TRIAL_EVERY  # ~2 of 5 frames here see a new fit pattern
    new_fit = [t for t in range(T) if "new fit pattern" in events[t]]
    assert len(new_fit) > 20
    beside = [t for t in new_fit if "trial" in events[t]]
    # a trial beside a new fit pattern only after TRIAL_LATE_FRAMES frames of new patterns before it
    # (or the next frame's workspace, built after a trial that changed the strength: the next frame finds it built)
    bad = [t for t in beside if not all("new fit pattern" in events[t - d] for d in range(1, mk.TRIAL_LATE_FRAMES + 1))
           and t not in changed]
    assert not bad, [(t, events[t - 3:t + 2]) for t in bad[:3]]


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


def test_a_prepared_pattern_is_known_and_solves_as_an_unprepared_one():
    """FrameQP.prepare (kalman builds the next frame's workspace a frame ahead): the step finds it built and solves
    as if it had built it itself."""
    from solvers.qp import FrameQP

    B, rng, n, m = _problem()
    seen = np.ones(n, bool)
    seen[[2, 7]] = False
    target = B @ rng.uniform(0, 1, m) + rng.normal(0, 0.01, 3 * n)
    prepared, plain = (FrameQP(B, np.zeros(m), np.ones(m), ridge=0.1) for _ in range(2))
    assert not prepared.knows(seen)
    prepared.prepare(seen)
    assert prepared.knows(seen) and prepared.cached_patterns == 1
    np.testing.assert_array_equal(prepared.step(target, seen), plain.step(target, seen))
    assert prepared.cached_patterns == 1  # the step built nothing more


def test_a_marker_space_trial_begun_on_its_frame_scores_as_one():
    """At many shapes (the marker-space path: 8 markers, 80 shapes and a pose) a known pattern's trial is begun
    on the frame it is due (its first passes) and finished on the next, with the score of a whole trial (solved
    exactly, the default: with ``frame_passes`` each frame's call is bounded, so a split trial runs more passes
    than a whole one)."""
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


def test_workspaces_built_ahead_for_a_changed_strength_keep_the_weights_bit_for_bit(monkeypatch):
    """A trial that changes the strength builds the next frame's workspace on the new strength's fit (issue 39: that
    frame's fit built it, ~100 µs over a known pattern); the trials stay on their frames, the weights are those of a
    stream that builds only the workspaces it always did."""
    from livecap.modes import marker_kalman as mk

    p = _face()
    T = 300
    X, valid = _bursty_take(p, 5, T, 0.3, 3, 0.5)
    built = []

    def run():
        solver = mk.kalman_mode(p, {"rate": 60.0})
        out, trials = [], []
        for t in range(T):
            before = solver.selector.t
            out.append(solver.step(X[t], valid[t]))
            trials.append(solver.selector.t != before)
            built.append(solver._fresh is not None)
        return np.array(out), trials

    ahead, trials_ahead = run()
    assert any(built)  # the strength changed with its next pattern unknown to the new fit at least once

    def only_ahead(self, fit, ahead):  # the rule before: the next pattern built for the same fit only
        if ahead is not None:
            self._fit(self.selector.best).prepare(ahead)

    monkeypatch.setattr(mk.MarkerKalmanSolver, "_at_leisure", only_ahead)
    plain, trials_plain = run()
    assert trials_ahead == trials_plain
    np.testing.assert_array_equal(ahead, plain)


def test_the_compiled_trial_scores_as_the_numpy_fit_and_score_it_replaced():
    """observe_unbounded's kernel fits, clips, scores, decays and picks the strength in one call (issue 39): the same
    errors, counts and choice, bit for bit, as the fit w = G x + h and HeldOutStrength._score in numpy."""
    B, rng, n, m = _problem(5, n=15, m=6)
    lo, hi, mu, P = np.zeros(m), np.full(m, 0.7), rng.uniform(0, 1, m), np.eye(m) + 0.3
    grid = np.logspace(-2, 1, 3)
    fast = HeldOutStrength(B, lo, hi, mu, P, grid, decay=0.97, unbounded=True)
    ref = HeldOutStrength(B, lo, hi, mu, P, grid, decay=0.97, unbounded=True)
    for t in range(40):
        valid = rng.uniform(size=n) > 0.15
        target = B @ rng.uniform(0, 1, m) + rng.normal(0, 0.05, 3 * n)
        fill = rng.uniform(0, 1, m)
        elapsed = 1 + t % 3
        g, f = ref.t % len(grid), (ref.t // len(grid)) % ref.folds
        ref.t += 1
        rows, GT, h = ref._maps[g, f]
        x = np.array([target[r] if valid[r // 3] else sum(B[r, j] * fill[j] for j in range(m)) for r in rows])
        w = h.copy()
        for i in range(len(rows)):
            w += GT[i] * x[i]
        w = np.clip(w, lo, hi)
        held = ref._fold_markers[f][valid[ref._fold_markers[f]]]
        if len(held) and np.count_nonzero(valid & ref._outside[f]) >= 3:
            r = np.repeat(3 * held, 3) + np.tile(np.arange(3), len(held))
            ref._score(g, float(np.sum((B[r] @ w - target[r]) ** 2)), len(held), elapsed)
        fast.observe_unbounded(target, valid, fill, elapsed=elapsed)
        np.testing.assert_allclose(fast.err, ref.err, rtol=1e-13, atol=0)
        np.testing.assert_array_equal(fast.count, ref.count)
        assert fast.best == ref.best
    assert ref._counted


def test_every_strengths_fit_reads_one_data_term():
    """The fits at each prior strength and the trials share B'M^2 (issue 39: a frame reads all of it, and a fit
    taking over from another found its own copy out of the caches), as built at reset and as built on first use."""
    from livecap.modes import marker_kalman as mk

    solver = mk.kalman_mode(_face(), {"rate": 60.0})
    assert len({id(fit._BtD) for fit in solver._fits.values()}) == 1
    # the trials' QPs too (issue 39, 72 x 1000: one 1.7 MB copy in the caches for the fit and the trial, not six)
    assert {id(qp._BtD) for qp in solver.selector.qps} == {id(solver._fits[0]._BtD)}
    first = solver._fits[0]
    solver._fits = {0: first}
    assert solver._fit(3)._BtD is first._BtD
