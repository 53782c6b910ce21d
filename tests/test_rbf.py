"""Example-based RBF blending (Pyun et al. 2003 §3–4): exact at keys, continuous between them."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.rbf import KeyBlendSolver, RBFBlend, cubic_bspline, feature_matrix


def _keys(seed: int, M: int, N: int, D: int):
    rng = np.random.default_rng(seed)
    return rng.normal(0, 5, (M, N)), rng.uniform(0, 1, (M, D))


def test_bspline_is_the_uniform_cubic():
    x = np.linspace(-3, 3, 601)
    b = cubic_bspline(x)
    assert b[300] == pytest.approx(2 / 3) and cubic_bspline(np.array([1.0]))[0] == pytest.approx(1 / 6)
    assert np.all(b[np.abs(x) >= 2] == 0) and np.all(b >= 0)
    # partition of unity of the integer shifts
    np.testing.assert_allclose(sum(cubic_bspline(np.linspace(0, 1, 11) - k) for k in range(-2, 3)), 1.0)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), M=st.integers(2, 25), N=st.integers(3, 60), D=st.integers(1, 8))
def test_reproduces_every_key(seed, M, N, D):
    V, T = _keys(seed, M, N, D)
    blend = RBFBlend(V, T, threshold=1e-12)
    for v, t in zip(V, T, strict=True):
        np.testing.assert_allclose(blend.evaluate(v), t, atol=1e-9)
    # cardinal functions: w_i(p_j) = delta_ij
    W = np.array([blend.key_weights(blend.F @ v) for v in V])
    np.testing.assert_allclose(W, np.eye(M), atol=1e-9)


def test_continuous_between_keys():
    V, T = _keys(1, 12, 30, 4)
    blend = RBFBlend(V, T)
    a, b = V[2], V[7]
    s = np.linspace(0, 1, 4001)
    path = np.array([blend.evaluate((1 - u) * a + u * b) for u in s])
    jumps = np.abs(np.diff(path, axis=0)).max()
    assert jumps < 5e-3  # 4000 steps: a C2 interpolant moves a little per step, never jumps
    # and refining the step shrinks the change proportionally (no discontinuity hiding in between)
    fine = np.array([blend.evaluate((1 - u) * a + u * b) for u in np.linspace(0.3, 0.3 + 1e-6, 3)])
    assert np.abs(np.diff(fine, axis=0)).max() < 1e-5


def test_pca_threshold_drops_small_directions():
    rng = np.random.default_rng(0)
    low = rng.normal(0, 1, (10, 3)) @ rng.normal(0, 1, (3, 40))  # rank 3
    assert feature_matrix(low).shape[0] == 3
    F = feature_matrix(low + rng.normal(0, 1e-6, low.shape), threshold=1e-5)
    assert F.shape[0] == 3
    np.testing.assert_allclose(F @ F.T, np.eye(3), atol=1e-12)


def test_coincident_keys_are_an_error():
    V, T = _keys(2, 5, 9, 2)
    V[3] = V[1]
    with pytest.raises(ValueError, match="coincide"):
        RBFBlend(V, T)


def test_solver_neutral_key_missing_markers_and_bad_input():
    V, T = _keys(3, 8, 30, 5)
    solver = KeyBlendSolver(V, T, np.zeros(5), np.ones(5))
    valid = np.ones(10, bool)
    np.testing.assert_allclose(solver.step(np.zeros((10, 3)), valid), 0.0, atol=1e-12)  # neutral -> rest
    np.testing.assert_allclose(solver.step(V[4].reshape(10, 3), valid), T[4], atol=1e-9)
    # one marker missing: the visible rows still pin the key (the keys span few directions)
    partial = valid.copy()
    partial[2] = False
    garbled = V[4].reshape(10, 3).copy()
    garbled[2] = np.nan
    np.testing.assert_allclose(solver.step(garbled, partial), T[4], atol=1e-6)
    last = solver.step(V[4].reshape(10, 3), valid)
    np.testing.assert_array_equal(solver.step(np.zeros((10, 3)), np.zeros(10, bool)), last)
    assert np.all(np.isfinite(solver.step(np.full((10, 3), 1e200), valid)))


def test_rbf_mode_from_rom_keys_recovers_key_poses(demo):
    from livecap.calibration.keys import keys_from_take
    from livecap.calibration.profile import calibrate
    from livecap.demo.performance import PerformanceSettings
    from livecap.demo.rom import rom_take
    from livecap.modes.registry import build_solver

    rig, layout = demo
    shapes = ["jawOpen", "mouthSmileLeft", "eyeBlinkLeft", "browInnerUp", "mouthPucker"]
    perf, specs = rom_take(rig, layout, PerformanceSettings(rate=60, noise_mm=0.0, occlusion=0.0,
                                                            head_degrees=0, head_mm=0, seed=3), shapes=shapes)
    profile = calibrate(rig, layout, perf.actor_neutral)
    keys = keys_from_take(perf.take, profile, specs)
    assert keys.names == shapes
    for spec, frame in zip(specs, keys.frames, strict=True):
        assert spec.start <= frame <= spec.end
        assert perf.weights[frame - perf.take.first_frame, rig.index(spec.name)] == pytest.approx(1.0)
    solver = build_solver("rbf", profile, {"keys": keys})
    for k, d in enumerate(keys.source):
        np.testing.assert_allclose(solver.step(d, np.ones(len(d), bool)), keys.target[k], atol=1e-9)
