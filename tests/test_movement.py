"""Offline movement matching (Seol et al. 2012 §4-6): structure, reference, boundaries, editing."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.blocks import IllPosedError
from solvers.movement import Edit, MovementMatching, fill_gaps
from solvers.prior import PCAPrior
from solvers.reference import solve_reference


def smooth_weights(rng: np.random.Generator, T: int, m: int, width: float = 8.0) -> np.ndarray:
    X = rng.normal(size=(T + 80, m))
    k = np.exp(-0.5 * (np.arange(-30, 31) / width) ** 2)
    Y = np.array([np.convolve(X[:, j], k / k.sum(), mode="same") for j in range(m)]).T[40:40 + T]
    return np.clip(0.4 + 2.5 * Y, 0.0, 1.0)


def case(seed: int, T: int = 20, n: int = 7, m: int = 5):
    rng = np.random.default_rng(seed)
    return rng, rng.normal(size=(3 * n, m)), rng.normal(size=(T, n, 3))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), T=st.integers(3, 25), noisy=st.booleans())
def test_equals_per_frame_solve_with_per_frame_boundaries(seed, T, noisy):
    """Seol §4: boundary values from the unconstrained per-frame fit reproduce that fit."""
    rng = np.random.default_rng(seed)
    n, m = 6, 4
    B = rng.normal(size=(3 * n, m))
    S = (smooth_weights(rng, T, m) @ B.T).reshape(T, n, 3)
    if noisy:
        S = S + rng.normal(0, 0.3, S.shape)
    per_frame = np.linalg.lstsq(B, S.reshape(T, -1).T, rcond=None)[0].T
    W = MovementMatching(B, start=per_frame[0], end=per_frame[-1]).solve(S)
    assert np.allclose(W, per_frame, atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), T=st.integers(2, 30), alpha=st.sampled_from([0.0, 0.05, 2.0]),
       beta=st.sampled_from([0.0, 0.3]), ridge=st.sampled_from([0.0, 0.01]),
       ends=st.sampled_from([("neutral", "neutral"), ("neutral", "free"), ("free", "fit"), ("free", "free")]),
       n_fixed=st.integers(0, 3), weighted=st.booleans())
def test_structured_solve_matches_literal_kronecker_eq5(seed, T, alpha, beta, ridge, ends, n_fixed, weighted):
    rng, B, S = case(seed, T)
    n, m = S.shape[1], B.shape[1]
    prior = PCAPrior.from_shapes(B) if alpha > 0 else None
    mw = rng.uniform(0.3, 3.0, n) if weighted else None
    fixed = {int(f): rng.normal(size=m) for f in rng.choice(T, size=min(n_fixed, T), replace=False)}
    mm = MovementMatching(B, alpha=alpha, prior=prior, beta=beta, ridge=ridge, marker_weights=mw,
                          start=ends[0], end=ends[1])
    bounds = mm.boundary_frames(S, np.ones((T, n), bool), fixed)
    if not bounds and alpha == 0 and beta == 0 and ridge == 0:
        with pytest.raises(IllPosedError):
            mm.solve(S, fixed=fixed)
        return
    W = mm.solve(S, fixed=fixed)
    R = solve_reference(B, S, bounds, alpha=alpha, prior=prior, beta=beta, marker_weights=mw, ridge=ridge)
    assert np.max(np.abs(W - R)) < 1e-8 * max(1.0, np.abs(R).max())
    for f, w in bounds.items():
        assert np.array_equal(W[f], w)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_exact_missing_markers_match_masked_reference(seed):
    rng, B, S = case(seed, T=25, n=8, m=5)
    valid = rng.random(S.shape[:2]) > 0.2
    prior = PCAPrior.from_shapes(B)
    mm = MovementMatching(B, alpha=0.2, prior=prior, beta=0.1, missing="exact")
    W = mm.solve(S, valid)
    R = solve_reference(B, S, mm.boundary_frames(S, valid), alpha=0.2, prior=prior, beta=0.1, valid=valid)
    assert np.max(np.abs(W - R)) < 1e-8


def test_gap_filling_is_close_to_the_exact_masked_solve(demo):
    rig, layout = demo
    B = layout.basis(rig)
    rng = np.random.default_rng(3)
    T, n, m = 300, layout.n_markers, rig.n_shapes
    truth = smooth_weights(rng, T, m, width=10)
    truth[0] = truth[-1] = 0
    S = (truth @ B.T).reshape(T, n, 3) + rng.normal(0, 0.2, (T, n, 3))
    valid = np.ones((T, n), bool)
    for _ in range(25):  # occlusion bursts
        i, t0, length = rng.integers(n), rng.integers(0, T - 30), rng.integers(3, 30)
        valid[t0:t0 + length, i] = False
    prior = PCAPrior.from_shapes(B)
    kw = dict(alpha=0.1, prior=prior, beta=0.1)
    exact = MovementMatching(B, missing="exact", **kw).solve(S, valid)
    filled = MovementMatching(B, **kw).solve(S, valid)
    naive = MovementMatching(B, fill_iterations=0, **kw).solve(S, valid)
    err_fill = np.abs(filled - exact).mean()
    assert err_fill < 0.1 * np.abs(exact - truth).mean()  # small next to the solve's own error
    assert err_fill <= np.abs(naive - exact).mean()  # iterating the rig-based refill helps
    assert np.isfinite(filled).all()


def test_fill_gaps_interpolates_offsets_and_keeps_observed_values():
    S = np.zeros((6, 2, 3))
    S[:, 0, 0] = np.arange(6.0)
    valid = np.ones((6, 2), bool)
    valid[2:4, 0] = False
    valid[:, 1] = False
    out = fill_gaps(np.where(valid[..., None], S, np.nan), valid)
    assert np.allclose(out[:, 0, 0], np.arange(6.0))  # linear gap: recovered exactly
    assert np.allclose(out[:, 1], 0.0)  # never seen: the fit (zero)


def test_ill_posed_without_any_boundary_or_anchor():
    _, B, S = case(0)
    with pytest.raises(IllPosedError):
        MovementMatching(B, start="free", end="free").solve(S)


@pytest.fixture
def solved():
    rng, B, _ = case(5, T=60, n=8, m=6)
    truth = smooth_weights(rng, 60, 6)
    S = (truth @ B.T).reshape(60, 8, 3) + rng.normal(0, 0.1, (60, 8, 3))
    mm = MovementMatching(B, alpha=0.3, prior=PCAPrior.from_shapes(B), beta=0.05)
    return mm, mm.solve(S), S


def test_edit_holds_at_k_and_leaves_outside_the_range_untouched(solved):
    mm, W, _ = solved
    E = mm.edit(W, [Edit(30, {1: 0.9, 4: -0.2}, (22, 41))])
    assert E[30, 1] == 0.9 and E[30, 4] == -0.2
    keep = [j for j in range(W.shape[1]) if j not in (1, 4)]
    assert np.array_equal(E[30, keep], W[30, keep])
    assert np.array_equal(E[:23], W[:23]) and np.array_equal(E[41:], W[41:])
    assert not np.allclose(E[23:30], W[23:30])  # the edit propagates inside
    # the correction fades towards the range ends
    corr = np.abs(E - W)[:, 1]
    assert corr[29] > corr[25] > corr[23] > 0 and corr[31] > corr[37] > corr[40] > 0


def test_a_no_op_edit_reproduces_the_solution(solved):
    """Inside [a, b] with a, b at their solved values, the optimum is the global optimum."""
    mm, W, _ = solved
    E = mm.edit(W, [Edit(30, {}, (10, 50))])
    assert np.allclose(E, W, atol=1e-9)


def test_a_no_op_edit_under_a_linear_term_reproduces_that_solution(solved):
    """The linear term of the solve, passed to the edit too, leaves the optimum where it was."""
    mm, _, S = solved
    mu = np.linspace(0.5, 2.0, 6)
    W = mm.solve(S, linear=mu)
    assert not np.allclose(W, mm.solve(S), atol=1e-6)
    assert np.allclose(mm.edit(W, [Edit(30, {}, (10, 50))], S, linear=mu), W, atol=1e-9)
    assert not np.allclose(mm.edit(W, [Edit(30, {}, (10, 50))], S), W, atol=1e-6)


def test_edits_compose(solved):
    mm, W, S = solved
    e1, e2 = Edit(20, {0: 1.0}, (12, 28)), Edit(45, {2: 0.1}, (38, 55))
    both = mm.edit(W, [e1, e2])
    one_then_other = mm.edit(mm.edit(W, [e1]), [e2], targets=S)
    assert np.allclose(both, one_then_other, atol=1e-12)  # disjoint ranges are independent
    # overlapping ranges merge: both edit frames hold, outside the union untouched
    e3 = Edit(25, {3: 0.7}, (15, 40))
    merged = mm.edit(W, [e1, e3])
    assert merged[20, 0] == 1.0 and merged[25, 3] == 0.7
    assert np.array_equal(merged[:13], W[:13]) and np.array_equal(merged[40:], W[40:])


def test_edit_rejects_bad_ranges(solved):
    mm, W, _ = solved
    with pytest.raises(ValueError):
        mm.edit(W, [Edit(10, {0: 1.0}, (12, 20))])
    with pytest.raises(ValueError):
        mm.edit(W, [Edit(10, {99: 1.0}, (5, 20))])


def test_clip_limits_offline():
    rng, B, S = case(2, T=40)
    mm = MovementMatching(B, np.zeros(5), np.ones(5), beta=0.1, limits="clip")
    W = mm.solve(5 * S)
    assert W.min() >= 0 and W.max() <= 1
