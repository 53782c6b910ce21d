"""Shapes the markers cannot tell apart are filled from the prior's conditional mean, not zeroed (issue 15).

Two shapes that move the markers identically: the data fix only their sum; the fit under a Gaussian
prior (solvers.qp.FrameQP with ``prior``, what ``kalman`` solves each frame) splits the sum as the
prior's conditional mean given it (Lewis et al. 2014 §7.9), while a plain ridge splits it evenly.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.qp import FrameQP


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), total=st.floats(0.2, 0.8), rho=st.floats(-0.6, 0.9))
def test_indistinguishable_shapes_get_the_prior_conditional_mean(seed, total, rho):
    rng = np.random.default_rng(seed)
    n = 12
    b = rng.normal(size=3 * n)
    other = rng.normal(size=3 * n)
    B = np.column_stack([b, b, other])  # shapes 0 and 1: the same marker motion
    mean = np.array([0.1, 0.35, 0.2])
    sd = np.array([0.1, 0.25, 0.2])
    cov = np.diag(sd) @ np.array([[1, rho, 0], [rho, 1, 0], [0, 0, 1]]) @ np.diag(sd)
    truth = np.array([0.6 * total, 0.4 * total, 0.3])
    fit = FrameQP(B, np.full(3, -5.0), np.full(3, 5.0), prior=(mean, np.linalg.inv(cov)), prior_weight=1e-7)
    w = fit.step((B @ truth).reshape(n, 3), np.ones(n, bool))
    u = np.array([1.0, 1.0])
    S = cov[:2, :2]
    conditional = mean[:2] + S @ u * (total - u @ mean[:2]) / (u @ S @ u)
    np.testing.assert_allclose(w[:2], conditional, atol=1e-4)
    np.testing.assert_allclose(w[2], truth[2], atol=1e-4)
    ridge = FrameQP(B, np.full(3, -5.0), np.full(3, 5.0), ridge=1e-7).step((B @ truth).reshape(n, 3), np.ones(n, bool))
    np.testing.assert_allclose(ridge[:2], [total / 2, total / 2], atol=1e-4)
