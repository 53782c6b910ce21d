"""Key reduction (Lewis §5.4): the error bound holds on every curve, and smooth curves need few keys."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.keyreduce import KeySettings, evaluate_keys, reduce_curve, reduce_curves


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), tol=st.sampled_from([0.001, 0.01, 0.05]), n=st.integers(1, 400),
       uneven=st.booleans())
def test_bound_holds_on_noisy_curves(seed, tol, n, uneven):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5, 1.5, n)) / 120.0 if uneven else np.arange(n) / 120.0
    y = np.clip(np.cumsum(rng.normal(0, 0.02, n)) + rng.normal(0, 0.005, n), -1, 2)
    k = reduce_curve(t, y, KeySettings(tol))
    assert k.frames[0] == 0 and k.frames[-1] == n - 1
    assert np.all(np.diff(k.frames) > 0)
    assert np.max(np.abs(evaluate_keys(k, t) - y)) <= tol + 1e-12


def test_a_cubic_needs_two_keys():
    t = np.linspace(0, 2, 241)
    y = 0.3 + 0.2 * t - 0.4 * t**2 + 0.15 * t**3
    k = reduce_curve(t, y, KeySettings(1e-6))
    assert len(k.frames) == 2
    np.testing.assert_allclose(k.out_tangents[0], 0.2, atol=1e-6)  # the derivative at t=0, per second


def test_smooth_curves_reduce_a_lot():
    t = np.arange(2400) / 120.0
    W = np.stack([0.5 + 0.5 * np.sin(2 * np.pi * f * t) for f in (0.1, 0.3, 0.7)], axis=1)
    keys = reduce_curves(t, W, KeySettings(0.01))
    for j, k in enumerate(keys):
        assert np.max(np.abs(evaluate_keys(k, t) - W[:, j])) <= 0.01
        assert len(k.frames) < 0.05 * len(t)


def test_shared_keys_keep_every_curve():
    from solvers.keyreduce import Keys, shared_keys

    rng = np.random.default_rng(0)
    t = np.arange(300) / 60.0
    W = np.cumsum(rng.normal(0, 0.01, (300, 4)), axis=0)
    keys = reduce_curves(t, W, KeySettings(0.005))
    frames, values, ins, outs = shared_keys(keys, t)
    for j in range(4):
        merged = Keys(frames, values[:, j], ins[:, j], outs[:, j])
        np.testing.assert_allclose(evaluate_keys(merged, t), evaluate_keys(keys[j], t), atol=1e-9)
