"""The whole-take prior strength in closed form (issue 39 item 2): the held-out errors of every strength equal those of
a fit per frame, and the offline ``kalman`` solve runs no bounded trial QP."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import solvers.prior_strength as ps


def _problem(seed: int, n: int, m: int, T: int, missing: float):
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(3 * n, m))
    A = rng.normal(size=(m - 2, m - 2))
    P = np.zeros((m, m))  # the last two columns unpenalised, as the pose's
    P[: m - 2, : m - 2] = A @ A.T + np.eye(m - 2)
    W = rng.normal(size=(T, m))
    X = W @ B.T + rng.normal(0, 0.5, (T, 3 * n))
    return B, rng.normal(size=m), P, X, rng.random((T, n)) >= missing


def _per_frame(B, mean, P, grid, X, ok, folds=5):
    """The same trials one fit per frame and strength: fold t % folds held out, the frame's seen markers trained on."""
    n = B.shape[0] // 3
    fold = np.random.default_rng(0).permutation(n) % folds
    err, count = np.zeros(len(grid)), 0
    for t in range(len(X)):
        held = fold == t % folds
        train, test = np.repeat(ok[t] & ~held, 3), np.repeat(ok[t] & held, 3)
        if not test.any():
            continue
        Bt = B[train]
        for g, a in enumerate(grid):
            w = np.linalg.solve(Bt.T @ Bt + a * P, Bt.T @ X[t][train] + a * P @ mean)
            r = B[test] @ w - X[t][test]
            err[g] += r @ r
        count += test.sum() // 3
    return err / count


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000), st.integers(16, 30), st.integers(4, 9), st.floats(0.0, 0.15))
def test_closed_form_trials_equal_a_fit_per_frame(seed, n, m, missing):
    B, mean, P, X, ok = _problem(seed, n, m, 40, missing)
    grid = np.logspace(-2, 1, 5)
    old = ps.FEW_MISSING
    ps.FEW_MISSING = n  # every frame, whatever it misses
    try:
        best, err, used = ps.take_strength(B, mean, P, grid, X, ok)
        kept: dict = {}
        again = [ps.take_strength(B, mean, P, grid, X, ok, factors=kept)[1] for _ in range(2)]  # factors kept
    finally:
        ps.FEW_MISSING = old
    want = _per_frame(B, mean, P, grid, X, ok)
    np.testing.assert_allclose(err, want, rtol=1e-8)
    np.testing.assert_array_equal(again[0], err)
    np.testing.assert_array_equal(again[1], err)
    assert best == int(np.argmin(want))
    # the kept frames and Woodbury systems serve other markers of the same validity (a second pose pass), not others
    rng = np.random.default_rng(seed)
    X2 = X + rng.normal(size=X.shape)
    ok2 = ok.copy()
    ok2[rng.integers(len(ok))] = False
    for x, v in ((X2, ok), (X2, ok2), (X, ok)):
        ps.FEW_MISSING = n
        try:
            fresh, reused = ps.take_strength(B, mean, P, grid, x, v)[1], ps.take_strength(B, mean, P, grid, x, v,
                                                                                         factors=kept)[1]
        finally:
            ps.FEW_MISSING = old
        np.testing.assert_array_equal(reused, fresh)


def test_frames_missing_many_markers_are_left_out_where_enough_miss_few():
    B, mean, P, X, ok = _problem(1, 20, 6, 60, 0.0)
    ok[::2, :8] = False  # every other frame misses 8 markers: more than FEW_MISSING of any fold's training markers
    _, _, used = ps.take_strength(B, mean, P, np.logspace(-2, 1, 4), X, ok)
    assert used == 30


def test_offline_kalman_runs_no_bounded_trial_and_checks_the_prior_on_few_frames(monkeypatch):
    """Before issue 39 item 2 the whole-take solve ran a held-out trial QP on every frame of both pose passes, and
    checked the prior on 120 frames to the streamed check's tolerance."""
    import livecap.modes.marker_kalman as mk
    from livecap.calibration.animation_prior import AnimationPrior
    from tests.test_marker_kalman import _face

    p = _face()
    m = len(p.names)
    rng = np.random.default_rng(2)
    A = rng.normal(0, 0.1, (m, m))
    p.prior = AnimationPrior(tuple(p.names), np.full(m, 0.4), A @ A.T + 0.02 * np.eye(m), 1000, ("other",))
    T = 400
    W = np.clip(0.5 + 0.4 * np.sin(np.arange(T)[:, None] * rng.uniform(0.01, 0.06, m) + rng.uniform(0, 6, m)), 0, 1)
    X = (W @ p.basis.T).reshape(T, -1, 3) + rng.normal(0, 0.2, (T, 40, 3))
    valid = rng.random((T, 40)) >= 0.05
    trials, checked = [], []
    observe, widen = mk.HeldOutStrength.observe, mk.widen_prior
    monkeypatch.setattr(mk.HeldOutStrength, "observe", lambda self, *a, **k: trials.append(1) or observe(self, *a, **k))
    monkeypatch.setattr(mk, "widen_prior", lambda *a, **k: checked.append((len(a[3]), k["tol"])) or widen(*a, **k))
    solver = mk.kalman_mode(p, {"rate": 60.0})
    out = solver.solve(X, valid)
    assert not trials and checked == [(mk.SUPPORT_TAKE_FRAMES, mk.SUPPORT_TAKE_TOL)]
    assert mk.SUPPORT_TAKE_FRAMES < 120 and mk.SUPPORT_TAKE_TOL > 1e-2
    assert np.sqrt(np.mean((out - W) ** 2)) < 0.06
