"""Per-frame QP (solvers/qp.py) against scipy's bounded least squares (Curio et al. 2006 §2.3)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import lsq_linear

from solvers.qp import FrameQP


def _problem(seed: int, n: int, m: int):
    rng = np.random.default_rng(seed)
    B = rng.normal(0, 3, (3 * n, m))
    lo = rng.uniform(-1, 0, m)
    hi = lo + rng.uniform(0.2, 1.5, m)
    w = rng.uniform(lo - 0.8, hi + 0.8)  # well outside the box: several bounds active
    s = B @ w + rng.normal(0, 0.3, 3 * n)
    return B, lo, hi, s


def _reference(B, lo, hi, s, ridge=0.0):
    m = B.shape[1]
    A = np.vstack([B, np.sqrt(ridge) * np.eye(m)])
    return lsq_linear(A, np.concatenate([s, np.zeros(m)]), bounds=(lo, hi), method="bvls", tol=1e-14).x


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(4, 20), m=st.integers(1, 12),
       ridge=st.sampled_from([0.0, 1e-3, 0.5]))
def test_agrees_with_lsq_linear_including_active_bounds(seed, n, m, ridge):
    B, lo, hi, s = _problem(seed, n, m)
    w = FrameQP(B, lo, hi, ridge=ridge).step(s.reshape(n, 3), np.ones(n, bool))
    ref = _reference(B, lo, hi, s, ridge)
    np.testing.assert_allclose(w, ref, atol=1e-6)


def test_bounds_really_are_active_in_these_problems():
    hits = 0
    for seed in range(20):
        B, lo, hi, s = _problem(seed, 10, 8)
        ref = _reference(B, lo, hi, s)
        hits += int(np.sum(np.isclose(ref, lo) | np.isclose(ref, hi)))
    assert hits > 20


def test_unconstrained_solution_when_no_bound_is_active():
    rng = np.random.default_rng(3)
    B = rng.normal(0, 2, (60, 6))
    w_true = rng.uniform(0.3, 0.7, 6)
    s = B @ w_true + rng.normal(0, 0.01, 60)
    w = FrameQP(B, np.full(6, -10.0), np.full(6, 10.0)).step(s.reshape(20, 3), np.ones(20, bool))
    np.testing.assert_allclose(w, np.linalg.lstsq(B, s, rcond=None)[0], atol=1e-9)


def test_missing_markers_drop_rows_and_cache_per_pattern():
    B, lo, hi, s = _problem(5, 15, 6)
    qp = FrameQP(B, lo, hi, ridge=1e-3, cache_size=2)
    for k in range(4):
        valid = np.ones(15, bool)
        valid[k : k + 3] = False
        rows = np.repeat(valid, 3)
        w = qp.step(np.where(rows, s, np.nan).reshape(15, 3), valid)  # NaN at missing markers is ignored
        np.testing.assert_allclose(w, _reference(B[rows], lo, hi, s[rows], 1e-3), atol=1e-6)
    assert qp.cached_patterns == 2  # bounded


def test_never_nan_never_raises():
    B, lo, hi, s = _problem(1, 6, 4)
    B[:, 0] = 0.0  # a shape no marker sees: H singular without ridge
    qp = FrameQP(B, lo, hi)
    w = qp.step(s.reshape(6, 3), np.ones(6, bool))
    assert np.all(np.isfinite(w)) and np.all((w >= lo) & (w <= hi))
    assert np.all(np.isfinite(qp.step(np.full((6, 3), np.nan), np.ones(6, bool))))
    assert np.all(np.isfinite(qp.step(s.reshape(6, 3), np.zeros(6, bool))))
    assert np.all(np.isfinite(qp.step(np.full((6, 3), 1e300), np.ones(6, bool))))
    np.testing.assert_array_equal(qp.step(np.zeros(5), np.ones(6, bool)), qp.step(np.zeros(5), np.ones(6, bool)))


def test_temporal_term_matches_its_closed_form_and_smooths():
    B, lo, hi, s = _problem(9, 12, 5)
    lo, hi = np.full(5, -50.0), np.full(5, 50.0)
    qp = FrameQP(B, lo, hi, temporal=20.0)
    w1 = qp.step(s.reshape(12, 3), np.ones(12, bool))
    expect = np.linalg.solve(B.T @ B + 20 * np.eye(5), B.T @ s)  # previous weights 0 after reset
    np.testing.assert_allclose(w1, expect, atol=1e-8)
    w2 = qp.step(s.reshape(12, 3), np.ones(12, bool))
    np.testing.assert_allclose(w2, np.linalg.solve(B.T @ B + 20 * np.eye(5), B.T @ s + 20 * w1), atol=1e-8)
    qp.reset()
    np.testing.assert_allclose(qp.step(s.reshape(12, 3), np.ones(12, bool)), w1, atol=1e-10)


def test_marker_weights_scale_rows():
    B, lo, hi, s = _problem(4, 10, 4)
    mw = np.linspace(0.2, 2.0, 10)
    w = FrameQP(B, lo, hi, marker_weights=mw).step(s.reshape(10, 3), np.ones(10, bool))
    D = np.repeat(mw, 3)[:, None]
    np.testing.assert_allclose(w, _reference(D * B, lo, hi, D[:, 0] * s), atol=1e-6)


def test_qp_mode_on_demo_profile(demo):
    from livecap.calibration.profile import calibrate
    from livecap.modes.registry import build_solver

    rig, layout = demo
    profile = calibrate(rig, layout, layout.marker_rig(rig).neutral)
    solver = build_solver("qp", profile, {"ridge": 1e-4})
    w_true = np.zeros(rig.n_shapes)
    w_true[[1, 5, 9]] = [0.8, 0.3, 0.5]
    target = (profile.basis @ w_true).reshape(-1, 3)
    np.testing.assert_allclose(solver.step(target, np.ones(layout.n_markers, bool)), w_true, atol=2e-3)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 12), m=st.integers(1, 10), free=st.integers(0, 4),
       alpha=st.sampled_from([1e-3, 0.1, 10.0]), missing=st.floats(0.0, 0.8))
def test_cond_bound_is_below_the_smallest_eigenvalue(seed, n, m, free, alpha, missing):
    """_CondBound's lambda_min(H) lower bound (fixed part PD on S, zero on the unpenalised U, as the pose
    columns beside a prior) must hold on every visibility pattern, so a skipped conditioning check is safe."""
    from solvers.qp import _CondBound

    rng = np.random.default_rng(seed)
    B = rng.normal(0, 3, (3 * n, m + free))
    A = rng.normal(size=(m, m))
    C = np.zeros((m + free, m + free))
    C[:m, :m] = alpha * (A @ A.T / m + 0.01 * np.eye(m))
    bound = _CondBound(C, B)
    rows = np.repeat(rng.random(n) > missing, 3)
    H = B[rows].T @ B[rows] + C
    assert bound.lambda_min(H) <= np.linalg.eigvalsh(H)[0] * (1 + 1e-9) + 1e-12


def test_a_warm_start_changes_the_passes_not_the_solution():
    """FrameQP.warm (the held-out trials start from the last frame's fit) must give the solution of a start
    from anywhere else."""
    B, lo, hi, s = _problem(3, 12, 9)
    seen = np.ones(12, bool)
    seen[[2, 7]] = False
    cold, warm = FrameQP(B, lo, hi, ridge=1e-3), FrameQP(B, lo, hi, ridge=1e-3)
    cold.step(np.zeros(36), np.ones(12, bool))
    warm.step(np.zeros(36), np.ones(12, bool))
    target = s.reshape(12, 3)
    warm.warm(cold.step(target, np.ones(12, bool)))
    np.testing.assert_allclose(warm.step(target, seen), _reference(B[np.repeat(seen, 3)], lo, hi,
                                                                 s[np.repeat(seen, 3)], 1e-3), atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 8), spread=st.sampled_from([1.0, 1e-4, 1e-9]))
def test_compiled_smallest_eigenvalue_matches_eigvalsh_and_never_exceeds_it(seed, n, spread):
    from solvers.qp_kernels import smallest_eigenvalue

    rng = np.random.default_rng(seed)
    Q = np.linalg.qr(rng.normal(size=(n, n)))[0]
    lam = np.sort(rng.uniform(spread, 1, n)) * 10.0 ** rng.integers(-3, 4)
    A = (Q * lam) @ Q.T
    A = (A + A.T) / 2
    got, ref = smallest_eigenvalue(A), np.linalg.eigvalsh(A)[0]
    assert got <= ref and got == pytest.approx(ref, abs=1e-10 * lam.sum())


@pytest.mark.parametrize("temporal", [0.0, 0.3])
def test_a_take_at_once_equals_stepping_it(temporal):
    """step_take: the same weights and end state as ``step`` frame by frame, across pattern changes, frames with
    no marker, NaN coordinates and block boundaries."""
    from solvers.sparse_fit import HysteresisSparseFit

    B, lo, hi, _ = _problem(5, 10, 8)
    rng = np.random.default_rng(6)
    T = 90
    S = (B @ rng.uniform(lo, hi, (T, 8)).T).T.reshape(T, 10, 3) + rng.normal(0, 0.2, (T, 10, 3))
    valid = rng.random((T, 10)) > 0.15
    valid[20] = False
    S[33, 4, 1] = np.nan
    S[50, 2] = np.inf
    valid[50, 2] = False  # a missing marker may hold anything
    for make in (lambda: FrameQP(B, lo, hi, ridge=0.1, temporal=temporal),
                 lambda: HysteresisSparseFit(B, lo, hi, 0.1, np.full(8, 2.0), np.full(8, 0.5))):
        a, b = make(), make()
        stepped = np.array([a.step(S[t], valid[t]) for t in range(T)])
        taken = b.step_take(S, valid, block=16)
        assert np.abs(taken - stepped).max() <= 1e-9
        assert np.abs(a.step(S[0], valid[0]) - b.step(S[0], valid[0])).max() <= 1e-9
        assert np.isfinite(taken).all() and np.ptp(taken, axis=0).max() > 0.1


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 12), m=st.integers(1, 10), free=st.integers(0, 4),
       missing=st.floats(0.0, 0.5))
def test_a_patterns_compiled_hessian_is_the_downdate_of_the_all_seen_one(seed, n, m, free, missing):
    """pattern_hessian (one call per new visibility pattern, issue 39): H_all less the missing markers' weighted rows,
    its trace, and the unpenalised block's smallest eigenvalue, as the numpy expressions it replaced give them."""
    from solvers.qp_kernels import pattern_hessian

    rng = np.random.default_rng(seed)
    B = rng.normal(0, 3, (3 * n, m + free))
    w = np.repeat(rng.uniform(0.2, 2.0, n), 3)
    H_all = B.T @ (B * w[:, None]) + np.diag(np.r_[rng.uniform(0.1, 1, m), np.zeros(free)])
    seen = rng.random(n) >= missing
    miss = ~np.repeat(seen, 3)
    ref = H_all - B[miss].T @ (B[miss] * w[miss, None])
    H = np.empty_like(H_all)
    trace, s2 = pattern_hessian(H_all, B, w, seen, m, m + free, H)
    np.testing.assert_allclose(H, ref, rtol=0, atol=1e-12 * np.abs(H_all).max())
    assert np.array_equal(H, H.T) and trace == pytest.approx(np.trace(ref), rel=1e-12)
    if free:
        assert s2 == pytest.approx(np.linalg.eigvalsh(ref[m:, m:])[0], abs=1e-9 * np.abs(H_all).max())
    else:
        assert s2 == np.inf


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(3, 12), m=st.integers(1, 10), free=st.integers(1, 4),
       missing=st.integers(1, 3))
def test_a_patterns_workspace_in_one_call_is_the_one_built_call_by_call(seed, n, m, free, missing):
    """pattern_workspace (a new visibility pattern's rows, H, its check's numbers and the box QP's state in one call,
    issue 39) against pattern_hessian and BoxQP built as before: equal bit for bit, and FrameQP's workspaces (a few
    markers missing, weight space) are built by it and solve as a solver built from H does."""
    from solvers.box_qp import BoxQP
    from solvers.qp_kernels import pattern_hessian, pattern_workspace

    rng = np.random.default_rng(seed)
    B = rng.normal(0, 3, (3 * n, m + free))
    lo, hi = np.r_[np.zeros(m), np.full(free, -np.inf)], np.r_[np.ones(m), np.full(free, np.inf)]
    P = np.diag(np.r_[rng.uniform(0.5, 2, m), np.zeros(free)])
    qp = FrameQP(B, lo, hi, prior=(rng.uniform(0, 1, m + free), P), prior_weight=0.3)
    qp.step(B @ rng.uniform(0, 1, m + free), np.ones(n, bool))
    seen = np.ones(n, bool)
    seen[rng.choice(n, min(missing, n // 2), replace=False)] = False
    rows, H, trace, s2, *state = pattern_workspace(qp._H_all, qp.basis, qp._row_w, seen, *qp._cond.span,
                                                   qp._limits[2])
    H_ref = np.empty_like(qp._H_all)
    ref = pattern_hessian(qp._H_all, qp.basis, qp._row_w, seen, *qp._cond.span, H_ref)
    box = BoxQP(H_ref, lo, hi, limit_rows=qp._limits[2])
    assert np.array_equal(rows, np.repeat(seen, 3)) and np.array_equal(H, H_ref) and (trace, s2) == ref
    for a, b in zip(state, (box._V, box._I, box._meta), strict=False):
        assert np.array_equal(a, b)
    assert state[-1] == box.tol
    ws = qp._workspace(seen.tobytes(), seen)
    assert ws._box is not None and np.array_equal(ws.rows, rows)
    f = rng.normal(0, 1, m + free)
    x = ws.box.solve(f)
    assert x is not None and np.array_equal(x, BoxQP(ws.H, lo, hi).solve(f))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(4, 12), m=st.integers(2, 10), missing=st.integers(0, 2))
def test_fits_at_two_strengths_share_their_data_term_and_solve_as_alone(seed, n, m, missing):
    """``like`` (kalman's fits at each prior strength, issue 39): one B'M^2 array for both, the weights bit for bit
    those of a fit with its own copy; not shared where the marker weights differ."""
    rng = np.random.default_rng(seed)
    B, lo, hi, s = _problem(seed, n, m)
    prior = (rng.uniform(0, 1, m), np.diag(rng.uniform(0.5, 2, m)))
    first = FrameQP(B, lo, hi, prior=prior, prior_weight=0.1)
    shared = FrameQP(B, lo, hi, prior=prior, prior_weight=2.0, like=first)
    alone = FrameQP(B, lo, hi, prior=prior, prior_weight=2.0)
    assert shared._BtD is first._BtD and np.array_equal(alone._BtD, first._BtD)
    assert FrameQP(B, lo, hi, marker_weights=np.full(n, 0.5), like=first)._BtD is not first._BtD
    for _ in range(3):
        seen = np.ones(n, bool)
        seen[rng.choice(n, missing, replace=False)] = False
        target = (s + rng.normal(0, 0.3, 3 * n)).reshape(n, 3)
        assert np.array_equal(shared.step(target, seen), alone.step(target, seen))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(4, 14), m=st.integers(2, 10), missing=st.integers(0, 3),
       strength=st.sampled_from([1e-3, 0.1, 10.0]))
def test_a_fit_warmed_from_another_strengths_solution_reaches_its_own_optimum(seed, n, m, missing, strength):
    """kalman warms a fit whose strength was not fitted last frame from the last frame's fit at the other strength
    (issue 39: its passes 10 -> 2.5 on the ICT takes): the same optimum, to 1e-9, as the fit from its own stale
    start."""
    rng = np.random.default_rng(seed)
    B, lo, hi, s = _problem(seed, n, m)
    prior = (rng.uniform(lo, hi), np.diag(rng.uniform(0.5, 2, m)))
    other = FrameQP(B, lo, hi, prior=prior, prior_weight=1.0)
    warm, stale = (FrameQP(B, lo, hi, prior=prior, prior_weight=strength) for _ in range(2))
    old = (B @ rng.uniform(lo, hi) + rng.normal(0, 0.3, 3 * n)).reshape(n, 3)
    warm.step(old, np.ones(n, bool))
    stale.step(old, np.ones(n, bool))
    seen = np.ones(n, bool)
    seen[rng.choice(n, missing, replace=False)] = False
    target = s.reshape(n, 3)
    warm.warm(other.step(target, seen))
    np.testing.assert_allclose(warm.step(target, seen), stale.step(target, seen), rtol=0, atol=1e-9)
