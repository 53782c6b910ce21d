"""The numba rank-1 up/downdates against a fresh numpy Cholesky factor of the changed matrix."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.cholupdate_kernels import lowrank_update


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 30), k=st.integers(1, 6), seed=st.integers(0, 2**31 - 1), down=st.booleans())
def test_updated_factor_is_fresh_cholesky(n, k, seed, down):
    rng = np.random.default_rng(seed)
    W = rng.standard_normal((n, n + k))
    X = rng.standard_normal((n, k))
    S = np.eye(n) + W @ W.T + (X @ X.T if down else 0.0)  # a downdate by X stays positive definite
    sign = np.full(k, -1.0 if down else 1.0)
    L = np.asfortranarray(np.linalg.cholesky(S))
    assert lowrank_update(L, np.asfortranarray(X.copy()), sign)
    np.testing.assert_allclose(np.tril(L), np.linalg.cholesky(S + sign * X @ X.T), rtol=0, atol=1e-9 * np.abs(S).max())


def test_downdate_past_definiteness_is_refused():
    L = np.asfortranarray(np.eye(3))
    assert not lowrank_update(L, np.asfortranarray(np.array([[0.0], [2.0], [0.0]])), np.array([-1.0]))
