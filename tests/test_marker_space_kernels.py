"""solvers.marker_space_kernels against the whole-array numpy a block-pivoting pass used before: the same bits."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.marker_space_kernels import repartition, rhs, x_and_gradient


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 60), seed=st.integers(0, 2**31 - 1), infinite=st.booleans())
def test_pass_kernels_equal_numpy(n, seed, infinite):
    rng = np.random.default_rng(seed)
    d = rng.random(n) + 1e-3
    dinv = 1.0 / d
    fG, z = rng.standard_normal(n), rng.standard_normal(n)
    lo, hi = -rng.random(n), rng.random(n)
    if infinite:
        lo[rng.random(n) < 0.3], hi[rng.random(n) < 0.3] = -np.inf, np.inf
    state = rng.integers(0, 3, n)
    at_lo, at_hi = (state == 1) & np.isfinite(lo), (state == 2) & np.isfinite(hi)
    F = ~(at_lo | at_hi)
    xA = np.where(at_lo, lo, np.where(at_hi, hi, 0.0))
    np.testing.assert_array_equal(rhs(fG, dinv, lo, hi, at_lo, at_hi), np.where(F, -fG * dinv, xA))
    x, g = x_and_gradient(z, fG, d, dinv, lo, hi, at_lo, at_hi)
    x_ref = np.where(F, -(fG + z) * dinv, xA)
    np.testing.assert_array_equal(x, x_ref)
    np.testing.assert_array_equal(g, d * x_ref + z + fG)
    lo1, hi1, wrong = repartition(x, g, lo, hi, at_lo, at_hi)
    lo_ref = np.where(F, x <= lo, at_lo & (g >= 0))
    hi_ref = np.where(F, x >= hi, at_hi & (g <= 0))
    np.testing.assert_array_equal(lo1, lo_ref)
    np.testing.assert_array_equal(hi1, hi_ref)
    assert wrong == np.count_nonzero((lo_ref != at_lo) | (hi_ref != at_hi))
