"""benchmarks.prior_oracle's covariances by the markers' evidence (issue 41.2): the evidence against a dense
Gaussian, EM's covariance against the one that drew the frames, the mixture's pick."""

import numpy as np
from scipy.stats import multivariate_normal

from benchmarks.prior_oracle import evidence_cov, held_out_ratio, log_evidence, mixture
from solvers.prior_support import POSE_VARIANCE


def _scene(seed: int, frames: int, cov: np.ndarray, noise: float = 0.1, n: int = 8, hidden: float = 0.1):
    rng = np.random.default_rng(seed)
    m = len(cov)
    B = rng.normal(size=(3 * n, m))
    E = rng.normal(size=(3 * n, 2))
    mean = rng.uniform(0.1, 0.3, m)
    W = rng.multivariate_normal(mean, cov, frames)
    X = W @ B.T + rng.normal(size=(frames, 2)) @ E.T + noise * rng.normal(size=(frames, 3 * n))
    valid = rng.random((frames, n)) > hidden
    return B, E, mean, X, valid


def test_log_evidence_is_the_dense_gaussian_on_each_frames_seen_markers():
    cov = np.diag([0.04, 0.01, 0.02]) + 0.005
    B, E, mean, X, valid = _scene(0, 5, cov)
    want = 0.0
    for x, ok in zip(X, valid, strict=True):
        rows = np.repeat(ok, 3)
        S = B[rows] @ cov @ B[rows].T + POSE_VARIANCE * E[rows] @ E[rows].T + 0.01 * np.eye(rows.sum())
        want += multivariate_normal(B[rows] @ mean, S).logpdf(x[rows])
    assert np.isclose(log_evidence(B, mean, cov, X, valid, E, 0.01), want, rtol=1e-9)


def test_em_moves_the_covariance_to_the_frames_and_its_hyperprior_holds_it():
    true = np.array([[0.04, 0.03, 0.0], [0.03, 0.04, 0.0], [0.0, 0.0, 0.01]])
    start = np.diag([0.01, 0.01, 0.04])
    B, E, mean, X, valid = _scene(1, 2000, true)
    C, s2, _ = evidence_cov(B, mean, start, X, valid, E, 0.25, prior_frames=1.0)
    assert np.abs(C - true).max() < 0.1 * np.abs(start - true).max()
    assert abs(s2 - 0.01) < 0.002
    held, _, _ = evidence_cov(B, mean, start, X, valid, E, 0.25, prior_frames=1e6)
    assert np.abs(held - start).max() < 0.01 * np.abs(start - true).max()


def test_mixture_takes_the_component_that_drew_the_frames_and_its_moments():
    a = np.diag([0.04, 0.001, 0.02])
    b = np.diag([0.001, 0.04, 0.02])
    B, E, mean, X, valid = _scene(2, 50, b)
    logp = np.array([log_evidence(B, mean, c, X, valid, E, 0.01) for c in (a, b)])
    mu, C, r = mixture([mean, mean], [a, b], logp)
    assert r[1] > 0.999 and np.allclose(C, b, atol=1e-3)
    mu, C, r = mixture([mean, mean + 0.1], [a, b], np.zeros(2))
    assert np.allclose(r, 0.5) and np.allclose(mu, mean + 0.05)
    assert np.allclose(C, 0.5 * (a + b) + 0.0025)


def test_held_out_half_picks_the_frames_covariance_only_where_the_others_do_not_fit():
    true = np.array([[0.04, 0.03, 0.0], [0.03, 0.04, 0.0], [0.0, 0.0, 0.01]])
    B, E, mean, X, valid = _scene(3, 400, true)
    ratios = [0.1, 1.0, np.inf]
    assert held_out_ratio(B, mean, np.diag([0.01, 0.01, 0.04]), X, valid, E, 0.01, ratios)[0] == 0.1
    assert held_out_ratio(B, mean, true, X, valid, E, 0.01, ratios)[0] == np.inf
