"""The robust mode over a whole take (livecap/modes/robust_take.py) gives the stepped stream's weights."""

import numpy as np
import pytest

from livecap.calibration.profile import calibrate
from livecap.demo.performance import PerformanceSettings, perform
from livecap.modes.registry import build_solver
from livecap.modes.robust import tune_profile
from livecap.modes.robust_take import whole_take
from livecap.offline.solve import prepare_targets, solve_take
from solvers.filters import CausalPolyFilter
from solvers.take_filters import causal_poly_take

TOL = 1e-8


def _take(rig, layout, seconds, occlusion, seed=4):
    perf = perform(rig, layout, PerformanceSettings(seconds=seconds, occlusion=occlusion, seed=seed))
    profile = calibrate(rig, layout, perf.actor_neutral)
    take, S, _, _ = prepare_targets(perf.take, profile)
    tune_profile(profile, S, take.valid, take.rate)
    return perf.take, profile, S, take.valid


def _stepped(solver, S, valid):
    solver.reset()
    return np.array([solver.step(S[t], valid[t]) for t in range(len(S))])


def _rest_changes(solver, S, valid):
    """Fraction of frames whose set of resting shapes differs from the previous frame's."""
    solver.reset()
    mf, fit = solver.marker_filter, solver.inner
    rest = np.array([fit.step(mf.step(S[t], np.broadcast_to(valid[t][:, None], S[t].shape)), valid[t]) <= 1e-9
                     for t in range(len(S))])
    return float(np.mean(np.any(rest[1:] != rest[:-1], axis=1)))


@pytest.mark.parametrize("occlusion", [0.0, 0.05, 0.30])
def test_demo_take_equals_the_stepped_stream(demo, occlusion):
    rig, layout = demo
    _, profile, S, valid = _take(rig, layout, 5.0, occlusion)
    solver = build_solver("robust", profile)
    W = whole_take(solver, S, valid)
    assert W is not None and W.shape == (len(S), rig.n_shapes)
    assert np.abs(W - _stepped(solver, S, valid)).max() <= TOL
    assert np.abs(W).max() > 0.1  # the take moves: the comparison is not of two rests


@pytest.mark.parametrize("occlusion", [0.05, 0.30])
def test_ict_take_equals_the_stepped_stream(ict, occlusion):
    rig, layout = ict
    _, profile, S, valid = _take(rig, layout, 4.0, occlusion)
    solver = build_solver("robust", profile)
    W = whole_take(solver, S, valid)
    assert np.abs(W - _stepped(solver, S, valid)).max() <= TOL


def test_hysteresis_switching_often_and_the_one_euro_stage(demo):
    rig, layout = demo
    _, profile, S, valid = _take(rig, layout, 4.0, 0.05, seed=9)
    options = {"z_enter": 1.5, "z_stay": 0.5, "noise_mm": 0.6}  # thresholds in the noise: shapes flicker
    solver = build_solver("robust", profile, options)
    assert _rest_changes(solver, S, valid) > 0.5
    assert np.abs(whole_take(solver, S, valid) - _stepped(solver, S, valid)).max() <= TOL
    one_euro = build_solver("robust", profile, {"weight_filter": "1e"})
    assert np.abs(whole_take(one_euro, S, valid) - _stepped(one_euro, S, valid)).max() <= TOL


def test_solve_take_uses_it_and_other_modes_step(demo):
    rig, layout = demo
    raw, profile, S, valid = _take(rig, layout, 3.0, 0.05)
    solver = build_solver("robust", profile)
    seen = []
    solved = solve_take(raw, profile, solver, progress=lambda i, n: seen.append((i, n)))
    assert np.abs(solved.weights - _stepped(solver, S, valid)).max() <= TOL
    assert seen == [(len(S), len(S))]
    assert whole_take(build_solver("qp", profile), S, valid) is None


def test_causal_filter_over_the_take_equals_its_steps():
    rng = np.random.default_rng(2)
    T, n = 300, 7
    X = np.cumsum(rng.normal(size=(T, n, 3)), axis=0)
    valid = rng.random((T, n)) > 0.3
    valid[40:90, 2] = False  # a gap longer than the window
    valid[:15, 4] = False  # missing from the start
    # a partial window as thin as order + 1 samples far back (three 9-11 frames back in a quadratic's window of 12)
    # has ill-conditioned normal equations: there the two paths differ by up to 3e-10 (quadratic; the stream's own
    # error against the exact fit is 2.4e-10) and 1.2e-8 (cubic) at values up to ~40, LU with pivoting in both
    for window, order in ((4, 2), (12, 2), (6, 1), (9, 3)):
        f = CausalPolyFilter(window, order)
        tol = 1e-9 if order <= 2 else 1e-7
        mask = np.broadcast_to(valid[..., None], X.shape)
        X0 = np.where(mask, X, 0.0)
        assert np.abs(causal_poly_take(X0, mask, window, order) - f.filter(X0, mask)).max() <= tol
        assert np.abs(causal_poly_take(X, None, window, order) - f.filter(X)).max() <= tol
        short = X0[:window - 2], mask[:window - 2]  # a take shorter than the window
        assert np.abs(causal_poly_take(*short, window, order) - f.filter(*short)).max() <= tol


def test_an_empty_take(demo):
    rig, layout = demo
    _, profile, S, valid = _take(rig, layout, 1.0, 0.0)
    assert whole_take(build_solver("robust", profile), S[:0], valid[:0]).shape == (0, rig.n_shapes)
