"""PCA prior (Seol et al. 2012 §5)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.prior import PCAPrior


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), m=st.integers(2, 8))
def test_prior_cost_is_the_mahalanobis_distance_of_pca_coefficients(seed, m):
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(3 * 10, m))
    train = rng.normal(size=(40, m))
    prior = PCAPrior.from_animation(B, train)
    w = rng.normal(size=m)
    v = prior.eigenvectors.T @ (B @ w - B @ train.mean(0))
    assert np.isclose(prior.cost(w), np.sum(v**2 / prior.eigenvalues))
    assert np.isclose(prior.cost(prior.mean_weights), 0.0)
    assert np.all(np.linalg.eigvalsh(prior.precision) > -1e-9)
    # the training faces are plausible on average: mean cost = number of components
    assert np.isclose(prior.cost(train).mean(), prior.n_components)


def test_shapes_prior_with_neutral_is_full_rank_and_without_is_not():
    B = np.random.default_rng(0).normal(size=(60, 12))
    with_neutral = PCAPrior.from_shapes(B)
    without = PCAPrior.from_shapes(B, include_neutral=False)
    assert with_neutral.n_components == 12 and without.n_components == 11
    assert np.linalg.matrix_rank(with_neutral.precision) == 12
    assert np.linalg.matrix_rank(without.precision, tol=1e-8) == 11


def test_threshold_drops_small_eigenvalues():
    B = np.random.default_rng(1).normal(size=(30, 6))
    train = np.zeros((50, 6))
    train[:, 0] = np.random.default_rng(2).normal(size=50)
    train[:, 1] = 1e-5 * np.random.default_rng(3).normal(size=50)
    assert PCAPrior.from_animation(B, train, threshold=1e-6).n_components == 1
    assert PCAPrior.from_animation(B, train, threshold=1e-14).n_components == 2
