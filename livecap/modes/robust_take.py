"""The ``robust`` mode over a whole recorded take, its stages run over the take instead of per frame.

The streaming solver (``robust.robust_solver``: causal marker filter -> hysteresis sparse fit ->
weight filter) is causal, so offline the same weights come from running each stage over the
whole take in turn: the marker filter as one FIR over time (``solvers.take_filters``), the sparse
fit frame by frame (its L1 term depends on the previous frame's rest set, which changes in most
frames of a real take, so it stays a sequence), then the weight filter over the fitted curves.
The result equals stepping the solver frame by frame from its reset state (tests/test_robust_take.py).
"""

from __future__ import annotations

import numpy as np

from solvers.filters import CausalPolyFilter, FilteredSolver
from solvers.sparse_fit import HysteresisSparseFit
from solvers.take_filters import causal_poly_take


def whole_take(solver, targets: np.ndarray, valid: np.ndarray) -> np.ndarray | None:
    """Weights (T x m) of ``solver`` over ``targets`` (T x n x 3) and ``valid`` (T x n), as stepping it
    from reset would give; None when the solver is not the robust mode's (then step it). Leaves it reset."""
    if not (isinstance(solver, FilteredSolver) and isinstance(solver.inner, HysteresisSparseFit)
            and isinstance(solver.marker_filter, CausalPolyFilter) and hasattr(solver.weight_filter, "filter")):
        return None
    valid = np.asarray(valid, dtype=bool)
    if not len(valid):
        return np.zeros((0, solver.inner.m))
    solver.reset()
    mf, fit = solver.marker_filter, solver.inner
    smoothed = causal_poly_take(targets, valid[..., None], mf.window, mf.order)
    W = solver.weight_filter.filter(fit.step_take(smoothed, valid))
    if solver.lower is not None:
        np.maximum(W, solver.lower, out=W)
        np.minimum(W, solver.upper, out=W)
    solver.reset()
    return W
