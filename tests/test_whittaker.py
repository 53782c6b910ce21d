"""The Whittaker smoother behind gap filling (solvers/whittaker.py, its compiled sweep solvers/whittaker_kernels.py)
and the numpy reference it is checked against (tests/whittaker_reference.py)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import solveh_banded

from solvers.whittaker import LAMBDAS, _penalty_bands, smooth
from tests.whittaker_reference import numpy_smooth, solve_pentadiagonal


@settings(max_examples=30, deadline=None)
@given(T=st.integers(3, 60), batch=st.integers(1, 4), seed=st.integers(0, 2**31 - 1))
def test_batched_solve_matches_lapack_banded_cholesky(T, batch, seed):
    rng = np.random.default_rng(seed)
    d0, e0, f0 = _penalty_bands(T)
    lam = 10.0 ** rng.uniform(-1, 7, batch)
    w = (rng.random((T, batch)) > 0.3).astype(float)
    w[rng.integers(0, T, 2)] = 1.0  # at least two seen samples: positive definite
    w[0] = w[-1] = 1.0
    d, e, f = d0[:, None] * lam + w, e0[:, None] * lam, f0[:, None] * lam
    b = rng.normal(size=(T, batch, 2))
    x = solve_pentadiagonal(d, e, f, b)
    for k in range(batch):
        ab = np.zeros((3, T))
        ab[0, 2:], ab[1, 1:], ab[2] = f[:, k], e[:, k], d[:, k]
        ref = solveh_banded(ab, b[:, k])
        np.testing.assert_allclose(x[:, k], ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_cross_validation_smooths_noise_and_follows_clean_tracks():
    rng = np.random.default_rng(1)
    t = np.arange(300)[:, None, None] / 120.0
    clean = 10 * np.sin(2 * np.pi * 1.0 * t) * np.ones((1, 2, 3))
    noisy = clean.copy()
    noisy[:, 1] += rng.normal(0, 0.5, noisy[:, 1].shape)
    seen = np.ones((300, 2), bool)
    x, lam = smooth(noisy, seen)
    assert lam[1] > lam[0]  # noise asks for more smoothing
    assert np.sqrt(np.mean((x[:, 1] - clean[:, 1]) ** 2)) < 0.3  # below the 0.5 mm noise
    assert np.abs(x[:, 0] - clean[:, 0]).max() < 0.05
    assert lam[0] in LAMBDAS


@settings(max_examples=40, deadline=None)
@given(T=st.integers(20, 200), k=st.integers(1, 6), c=st.integers(1, 3), missing=st.floats(0.0, 0.6),
       seed=st.integers(0, 2**31 - 1))
def test_compiled_smoother_equals_the_numpy_sweep(T, k, c, missing, seed):
    """Same smoothing chosen per track, same curves to rounding, on tracks with gaps anywhere (unseen samples
    hold garbage the smoother must not read) and with every candidate's GCV score in play."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)[:, None, None] / 60.0
    y = 5 * np.sin(2 * np.pi * rng.uniform(0.1, 3, (1, k, c)) * t) + rng.normal(0, rng.uniform(0, 1), (T, k, c))
    seen = rng.random((T, k)) >= missing
    seen[rng.integers(0, T, (2, k)), np.arange(k)] = True
    seen[0] = seen[-1] = True  # two seen samples at least, different frames
    y[~seen] = rng.choice([np.nan, 1e9, -3.0])
    x, lam = smooth(y, seen)
    x_ref, lam_ref = numpy_smooth(y, seen)
    np.testing.assert_array_equal(lam, lam_ref)
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-9 * max(1.0, np.abs(x_ref).max()))
