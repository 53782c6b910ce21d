"""Movement matching with the weight limits active (solvers/bounded.py, Seol et al. 2012 §4, §7):
the structured ADMM against an independent QP solver on the literal sparse system, limits,
inactive bounds, fixed frames, edits, the linear term, and Seol's argument (the bounded optimum
is no worse than any feasible point such as the clipped solve)."""

from __future__ import annotations

import numpy as np
import osqp
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.bounded import BoundedMovement
from solvers.movement import Edit, MovementMatching
from solvers.prior import PCAPrior
from solvers.reference import reference_system

TIGHT = {"tol": 1e-11, "max_iter": 20000}


def case(seed: int, T: int, n: int = 6, m: int = 4, scale: float = 3.0):
    rng = np.random.default_rng(seed)
    return rng, rng.normal(size=(3 * n, m)), scale * rng.normal(size=(T, n, 3))


def qp_reference(B, S, bounds, lo, hi, linear=None, **kw):
    """The literal sparse normal equations (solvers/reference.py) handed to OSQP with polishing."""
    T, m = len(S), B.shape[1]
    N, rhs, known, x = reference_system(B, S, bounds, **kw)
    q = -2.0 * rhs
    if linear is not None:
        q = q + np.broadcast_to(linear, (T, m)).reshape(-1)[~known]
    nu = int((~known).sum())
    if nu == 0:
        return x.reshape(T, m)
    prob = osqp.OSQP()
    prob.setup(sp.triu(2.0 * N).tocsc(), q, sp.identity(nu, format="csc"), np.tile(lo, T)[~known],
               np.tile(hi, T)[~known], eps_abs=1e-12, eps_rel=1e-12, max_iter=200000, polishing=True, verbose=False)
    x[~known] = prob.solve(raise_error=True).x
    return x.reshape(T, m)


def objective(B, S, bounds, W, linear=None, **kw):
    N, rhs, known, _ = reference_system(B, S, bounds, **kw)
    x = W.reshape(-1)[~known]
    lin = 0.0 if linear is None else float(np.broadcast_to(linear, W.shape).reshape(-1)[~known] @ x)
    return float(x @ (N @ x) - 2 * rhs @ x) + lin


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), T=st.integers(2, 18), alpha=st.sampled_from([0.0, 0.05, 1.0]),
       beta=st.sampled_from([0.0, 0.2]), ends=st.sampled_from([("neutral", "neutral"), ("neutral", "free"),
                                                                ("free", "free")]),
       n_fixed=st.integers(0, 2), with_linear=st.booleans())
def test_matches_an_independent_qp_solver_on_the_literal_system(seed, T, alpha, beta, ends, n_fixed, with_linear):
    rng, B, S = case(seed, T)
    m = B.shape[1]
    if ends == ("free", "free") and alpha == 0 and beta == 0 and n_fixed == 0:
        beta = 0.2  # otherwise ill-posed (tested in test_movement.py)
    prior = PCAPrior.from_shapes(B) if alpha > 0 else None
    lo, hi = np.full(m, -0.5), np.full(m, 1.5)
    fixed = {int(f): rng.uniform(-1, 2, m) for f in rng.choice(T, size=min(n_fixed, T), replace=False)}
    linear = rng.uniform(0, 5, (T, m)) if with_linear else None
    mm = MovementMatching(B, lo, hi, alpha=alpha, prior=prior, beta=beta, start=ends[0], end=ends[1],
                          limits="bound", bound_options=TIGHT)
    W = mm.solve(S, fixed=fixed, linear=linear)
    bounds = mm.boundary_frames(S, np.ones(S.shape[:2], bool), fixed)
    R = qp_reference(B, S, bounds, lo, hi, linear, alpha=alpha, prior=prior, beta=beta)
    assert mm.bounded_info is None or mm.bounded_info.converged
    assert np.max(np.abs(W - R)) < 1e-6
    for f, w in bounds.items():  # fixed frames hold exactly, even outside the limits
        assert np.array_equal(W[f], w)
    free = [t for t in range(T) if t not in bounds]
    assert np.all(W[free] >= lo) and np.all(W[free] <= hi)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), T=st.integers(3, 30), alpha=st.sampled_from([0.0, 0.3]))
def test_with_inactive_bounds_equals_the_unbounded_solve(seed, T, alpha):
    _, B, S = case(seed, T)
    m = B.shape[1]
    prior = PCAPrior.from_shapes(B) if alpha else None
    free = MovementMatching(B, alpha=alpha, prior=prior, beta=0.1).solve(S)
    wide = np.abs(free).max() + 1.0
    bounded = MovementMatching(B, np.full(m, -wide), np.full(m, wide), alpha=alpha, prior=prior, beta=0.1,
                               limits="bound").solve(S)
    assert np.max(np.abs(bounded - free)) < 1e-9


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), T=st.integers(4, 30), alpha=st.sampled_from([0.0, 0.05]))
def test_bounded_optimum_is_no_worse_than_clipping_or_range_pf(seed, T, alpha):
    """Seol §4 Fig. 3: clipping the unbounded solve, or clipping each frame's own fit, gives a
    feasible point; the bounded optimum's objective cannot exceed theirs."""
    _, B, S = case(seed, T)
    m = B.shape[1]
    prior = PCAPrior.from_shapes(B) if alpha else None
    lo, hi = np.zeros(m), np.ones(m)
    kw = dict(alpha=alpha, prior=prior, beta=0.05)
    W = MovementMatching(B, lo, hi, limits="bound", **kw).solve(S)
    clipped = MovementMatching(B, lo, hi, limits="clip", **kw).solve(S)
    pf = np.clip(np.linalg.lstsq(B, S.reshape(T, -1).T, rcond=None)[0].T, lo, hi)
    pf[0] = pf[-1] = 0.0
    bounds = {0: np.zeros(m), T - 1: np.zeros(m)}
    e = objective(B, S, bounds, W, **kw)
    assert e <= objective(B, S, bounds, clipped, **kw) + 1e-6 * abs(e)
    assert e <= objective(B, S, bounds, pf, **kw) + 1e-6 * abs(e)


def test_limits_hold_per_shape_and_the_result_stays_near_the_solve():
    rng, B, S = case(4, 60, n=8, m=5, scale=6.0)
    lo, hi = np.array([-0.5, 0, 0, -1, 0]), np.array([1.5, 1, 0.5, 1, 2])
    mm = MovementMatching(B, lo, hi, alpha=0.1, prior=PCAPrior.from_shapes(B), beta=0.1, limits="bound")
    W = mm.solve(S)
    assert mm.bounded_info.converged and mm.bounded_info.iterations > 1
    assert np.all(W[1:-1] >= lo) and np.all(W[1:-1] <= hi)
    assert np.any(np.isclose(W, lo)) and np.any(np.isclose(W, hi))  # the limits are active


def test_edits_hold_exactly_and_the_re_solve_respects_the_limits():
    rng, B, S = case(6, 60, n=8, m=5, scale=4.0)
    m = 5
    lo, hi = np.zeros(m), np.ones(m)
    mm = MovementMatching(B, lo, hi, alpha=0.1, prior=PCAPrior.from_shapes(B), beta=0.05, limits="bound")
    W = mm.solve(S)
    E = mm.edit(W, [Edit(30, {1: 1.3, 2: 0.2}, (20, 42))])  # an artist may pose past the limits
    assert E[30, 1] == 1.3 and E[30, 2] == 0.2
    assert np.array_equal(E[:21], W[:21]) and np.array_equal(E[42:], W[42:])
    inside = np.r_[21:30, 31:42]
    assert np.all(E[inside] >= lo) and np.all(E[inside] <= hi)
    assert not np.allclose(E[inside], W[inside])


def test_linear_term_without_bounds_matches_the_literal_normal_equations():
    rng, B, S = case(8, 20)
    m = B.shape[1]
    mu = rng.uniform(0, 3, m)
    W = MovementMatching(B, beta=0.1).solve(S, linear=mu)
    N, rhs, known, x = reference_system(B, S, {0: np.zeros(m), 19: np.zeros(m)}, beta=0.1)
    x[~known] = np.linalg.solve(N.toarray(), rhs - 0.5 * np.tile(mu, 20)[~known])
    assert np.max(np.abs(W - x.reshape(20, m))) < 1e-9


def test_rejects_crossed_limits_and_unknown_modes():
    _, B, _ = case(0, 5)
    mm = MovementMatching(B, np.ones(4), np.zeros(4), beta=0.1)
    with pytest.raises(ValueError):
        BoundedMovement(mm.blocks, mm.lower, mm.upper)
    with pytest.raises(ValueError):
        MovementMatching(B, limits="bounded")


@pytest.mark.parametrize("missing", ["fill", "exact"])
def test_missing_markers_keep_the_limits_and_no_nan(missing):
    rng, B, S = case(9, 40, n=8, m=5, scale=5.0)
    valid = rng.random(S.shape[:2]) > 0.15
    S[~valid] = np.nan
    lo, hi = np.zeros(5), np.ones(5)
    W = MovementMatching(B, lo, hi, alpha=0.1, prior=PCAPrior.from_shapes(B), beta=0.1, missing=missing,
                         limits="bound").solve(np.where(valid[..., None], S, 0.0), valid)
    assert np.isfinite(W).all() and W.min() >= 0 and W.max() <= 1
