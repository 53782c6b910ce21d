"""The Audio2Face-3D baseline (issue 41.7): its published terms do what they say."""

from __future__ import annotations

import numpy as np

from solvers.a2f_baseline import A2FSolve, symmetric_pairs


def test_pairs_and_a_shape_recovered_without_regularisation():
    names = ["jawOpen", "smile_L", "smile_R", "eyeBlinkLeft", "eyeBlinkRight"]
    assert sorted(symmetric_pairs(names)) == [(1, 2), (3, 4)]
    rng = np.random.default_rng(0)
    B = rng.normal(size=(30, 5))
    s = A2FSolve(B, np.zeros(5), np.ones(5), names, l1=0, l2=0, symmetry=0, temporal=0)
    np.testing.assert_allclose(s.step((B @ [0.7, 0, 0, 0, 0]).reshape(10, 3), np.ones(10, bool)),
                               [0.7, 0, 0, 0, 0], atol=1e-9)


def test_symmetry_and_temporal_terms_pull_as_published():
    names = ["a_L", "a_R"]
    B = np.eye(6)[:, :2]
    target = (B @ [1.0, 0.0]).reshape(2, 3)
    seen = np.ones(2, bool)
    free = A2FSolve(B, np.zeros(2), np.ones(2), names, l1=0, l2=0, symmetry=0, temporal=0).step(target, seen)
    tied = A2FSolve(B, np.zeros(2), np.ones(2), names, l1=0, l2=0, symmetry=100, temporal=0).step(target, seen)
    assert free[1] == 0 and tied[1] > 0.45 and abs(tied[0] - tied[1]) < 0.01
    slow = A2FSolve(B, np.zeros(2), np.ones(2), names, l1=0, l2=0, symmetry=0, temporal=5)
    assert slow.step(target, np.ones(2, bool))[0] < 0.01  # 500 x |w - w_prev|^2 against |w - 1|^2: barely moves
