"""The marker-space box QP (solvers/marker_space_qp.py): the KKT conditions and the dense solve's optimum, alone
and as FrameQP's path where the shapes far outnumber the marker coordinates."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import solvers.qp as qp_module
from solvers.box_qp import BoxQP
from solvers.marker_space_qp import MarkerSpaceQP
from solvers.pose_refine import RigidColumns
from solvers.qp import FrameQP


def _problem(rng, r: int, n: int, p: int, dmin: float = 1e-3):
    """r rows, n bounded weights (some limits infinite), p unpenalised unbounded columns (a pose)."""
    J = rng.normal(0, 2, (r, n + p))
    d = np.r_[rng.uniform(dmin, 2, n), np.zeros(p)]
    lo = np.r_[np.where(rng.random(n) < 0.1, -np.inf, rng.uniform(-1, 0, n)), np.full(p, -np.inf)]
    hi = np.r_[np.where(rng.random(n) < 0.1, np.inf, rng.uniform(0.1, 1.5, n)), np.full(p, np.inf)]
    f = rng.normal(0, 4, n + p)
    return J, d, lo, hi, f


def _kkt(H, f, lo, hi, x, tol):
    g = H @ x + f
    scale = tol * (1 + np.abs(H).max() * (1 + np.abs(x).max()) + np.abs(f).max())
    assert np.all(x >= lo) and np.all(x <= hi)
    free = (x > lo) & (x < hi)
    assert np.abs(g[free]).max(initial=0) <= scale
    assert np.all(g[(x == lo) & ~free] >= -scale) and np.all(g[(x == hi) & ~free] <= scale)


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), r=st.integers(3, 24), n=st.integers(1, 60), p=st.integers(0, 3),
       warm=st.booleans())
def test_kkt_and_the_dense_optimum(seed, r, n, p, warm):
    rng = np.random.default_rng(seed)
    J, d, lo, hi, f = _problem(rng, r, n, p)
    H = np.diag(d) + J.T @ J
    try:
        q = MarkerSpaceQP(J, d, lo, hi, max_iter=5000)
    except np.linalg.LinAlgError:
        assert p and np.linalg.matrix_rank(J[:, n:]) < p  # refused only where the rows do not fix the pose
        return
    x0 = np.clip(rng.normal(0, 1, n + p), lo, hi) if warm else np.clip(np.zeros(n + p), lo, hi)
    x = q.solve(f, x0)
    assert x is not None, "no convergence"
    _kkt(H, f, lo, hi, x, 1e-9)
    np.testing.assert_allclose(x, BoxQP(H, lo, hi).solve(f), atol=1e-7)


def test_kept_factor_over_a_sequence_of_solves():
    """Many frames on one pattern: the marker-space matrix updated by the changed columns, refreshed every REFRESH
    updates, gives each frame's optimum."""
    rng = np.random.default_rng(7)
    J, d, lo, hi, f = _problem(rng, 18, 90, 6, dmin=0.1)  # a ridge: a weak one lets block pivoting cycle longer
    lo[:90], hi[:90] = 0.0, 1.0
    H = np.diag(d) + J.T @ J
    q = MarkerSpaceQP(J, d, lo, hi)
    box = BoxQP(H, lo, hi)
    x = np.clip(np.zeros(96), lo, hi)
    passes = []
    for _ in range(200):  # frames: one signal, fresh noise
        g = f + rng.normal(0, 1.0, 96)
        x = q.solve(g, x)
        passes.append(q.iterations)
        np.testing.assert_allclose(x, box.solve(g), atol=1e-8)
    assert max(passes) > 1


def test_bounded_column_without_curvature_refused():
    with pytest.raises(ValueError, match="unbounded"):
        MarkerSpaceQP(np.ones((3, 2)), np.array([1.0, 0.0]), np.zeros(2), np.ones(2))


def _rig(n_markers: int, m: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    neutral = rng.normal(0, 40, (n_markers, 3))
    B = rng.normal(0, 2, (3 * n_markers, m))
    pose = RigidColumns(neutral)
    return pose.augment(B, np.zeros(m), np.ones(m), np.zeros(m), np.eye(m)), rng


@pytest.mark.parametrize("strength", [1e-2, 1.0])
def test_frameqp_marker_space_path_equals_weight_space(monkeypatch, strength):
    """kalman's fit at many shapes (pose columns, a ridge prior, markers dropping out): the same weights through
    the marker-space path as through the weight-space one."""
    (B, lo, hi, mean, P), rng = _rig(8, 80)
    fast = FrameQP(B, lo, hi, prior=(mean, P), prior_weight=strength)
    monkeypatch.setattr(qp_module, "MARKER_SPACE_RATIO", np.inf)
    slow = FrameQP(B, lo, hi, prior=(mean, P), prior_weight=strength)
    assert fast.marker_space and not slow.marker_space
    used = 0
    w_true = rng.uniform(0, 0.6, 80)
    for _ in range(60):
        w_true = np.clip(w_true + rng.normal(0, 0.1, 80), -0.2, 1.2)
        s = (B[:, :80] @ w_true + rng.normal(0, 0.3, 24)).reshape(8, 3)
        seen = rng.random(8) > 0.15
        a, b = fast.step(s, seen), slow.step(s, seen)
        np.testing.assert_allclose(a, b, atol=1e-7)
        used += int(np.count_nonzero((a > lo) & (a < hi)) >= 24)
    assert used > 20  # the marker-space path really ran
    assert any(ws.marker_space for ws in fast._models.values())


def test_small_rigs_keep_the_weight_space_path():
    (B, lo, hi, mean, P), _ = _rig(20, 50)  # 60 marker coordinates, 56 columns: as ICT (~53 shapes) or 72 x 150
    assert not FrameQP(B, lo, hi, prior=(mean, P), prior_weight=1.0).marker_space


def test_prepare_builds_every_seen_patterns_marker_space_solver():
    (B, lo, hi, mean, P), _ = _rig(8, 80)
    qp = FrameQP(B, lo, hi, prior=(mean, P), prior_weight=1.0)
    for drop in range(3):
        seen = np.ones(8, bool)
        seen[drop] = False
        qp.step(np.zeros((8, 3)), seen)
    assert all(ws.marker_space is None for ws in qp._models.values())  # zero weights free: not taken yet
    qp.prepare_marker_space()
    assert len(qp._models) == 3 and all(isinstance(ws.marker_space, MarkerSpaceQP) for ws in qp._models.values())
