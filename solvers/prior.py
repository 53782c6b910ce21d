"""Model-specific PCA prior on plausible target faces (Seol et al. 2012 §5).

The training "animation" is either the rig's own shapes taken as frames (frame j = shape j at
weight 1: a well-built rig spans its plausible faces by construction) or any supplied weight
animation of the target. Each training frame is mapped through the marker-space basis B, PCA
gives eigenvectors E (3n x h) and eigenvalues lambda_k, and the per-frame cost is

    E_prior(w) = v^T Lambda^-1 v,  v = E^T (B w - mean)                       (§5)

which is a quadratic form in the weights, (w - w_mean)^T P (w - w_mean) with the constant
m x m matrix P = (E^T B)^T Lambda^-1 (E^T B). Keeping it as (P, w_mean) is what lets the
movement solvers fold the prior into their constant blocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PCAPrior:
    precision: np.ndarray  # m x m, P = (E^T B)^T Lambda^-1 (E^T B)
    mean_weights: np.ndarray  # m, weights whose marker displacement is the training mean
    eigenvalues: np.ndarray  # h kept eigenvalues (mm^2), descending
    eigenvectors: np.ndarray  # 3n x h

    @property
    def n_components(self) -> int:
        return len(self.eigenvalues)

    def cost(self, weights: np.ndarray) -> np.ndarray:
        """E_prior per frame for ``weights`` (m,) or (T, m)."""
        d = np.atleast_2d(weights) - self.mean_weights
        c = np.einsum("ti,ij,tj->t", d, self.precision, d)
        return c if np.ndim(weights) == 2 else c[0]

    def gradient_constant(self) -> np.ndarray:
        """P w_mean: the constant the prior adds to every frame's right-hand side."""
        return self.precision @ self.mean_weights

    @classmethod
    def from_animation(cls, basis: np.ndarray, weights: np.ndarray, threshold: float = 1e-6) -> PCAPrior:
        """PCA of a target weight animation (T x m) seen through ``basis`` (3n x m).

        ``threshold`` drops eigenvalues below ``threshold * largest`` (Seol keep the h
        eigenvectors with nonzero eigenvalue; numerically "nonzero" needs a tolerance).
        """
        B = np.asarray(basis, dtype=np.float64)
        W = np.atleast_2d(np.asarray(weights, dtype=np.float64))
        if W.shape[1] != B.shape[1]:
            raise ValueError(f"prior animation has {W.shape[1]} weights, basis has {B.shape[1]} shapes")
        if len(W) < 2:
            raise ValueError("a PCA prior needs at least two training frames")
        w_mean = W.mean(0)
        X = (W - w_mean) @ B.T  # centred training faces, T x 3n
        _, sv, Vt = np.linalg.svd(X, full_matrices=False)
        lam = sv**2 / len(W)
        keep = lam > threshold * max(lam[0], 1e-300)
        return cls._from_axes(B, Vt[keep].T, lam[keep], w_mean)

    @classmethod
    def from_moments(cls, basis: np.ndarray, mean: np.ndarray, cov: np.ndarray, threshold: float = 1e-6) -> PCAPrior:
        """The same PCA from a weight mean (m) and covariance (m x m) instead of frames: the faces'
        covariance is B cov B^T (a Gaussian prior learned from animation, Lewis et al. 2014 §7.8-7.9,
        seen through this actor's basis)."""
        B = np.asarray(basis, dtype=np.float64)
        cov = np.asarray(cov, dtype=np.float64)
        if np.shape(mean) != (B.shape[1],) or cov.shape != (B.shape[1], B.shape[1]):
            raise ValueError(f"prior mean {np.shape(mean)} / covariance {cov.shape} do not fit {B.shape[1]} shapes")
        lam, V = np.linalg.eigh(B @ (0.5 * (cov + cov.T)) @ B.T)
        lam, V = lam[::-1], V[:, ::-1]
        keep = lam > threshold * max(lam[0], 1e-300)
        return cls._from_axes(B, V[:, keep], lam[keep], np.asarray(mean, dtype=np.float64))

    @classmethod
    def _from_axes(cls, B: np.ndarray, E: np.ndarray, lam: np.ndarray, w_mean: np.ndarray) -> PCAPrior:
        """The prior of principal axes E (3n x h) with variances lam, as a quadratic form in the weights."""
        EB = E.T @ B  # h x m
        P = EB.T @ (EB / lam[:, None])
        return cls(0.5 * (P + P.T), w_mean, lam, E)

    @classmethod
    def from_shapes(cls, basis: np.ndarray, threshold: float = 1e-6, include_neutral: bool = True) -> PCAPrior:
        """The rig's shapes as training frames (Seol §5, §7: "all the target blendshapes").

        ``include_neutral`` adds the neutral face as one more frame. Without it the centred
        shapes span only m-1 directions, the prior has no opinion along the last one, and the
        movement solve accumulates noise along it like a random walk (on the demo take the
        weight range grew from [-0.6, 0.6] to [-3.9, 5.1] at alpha 0.1).
        """
        m = np.asarray(basis).shape[1]
        W = np.eye(m)
        if include_neutral:
            W = np.vstack([np.zeros(m), W])
        return cls.from_animation(basis, W, threshold)


def build_prior(basis: np.ndarray, source: str | np.ndarray | None = "shapes", threshold: float = 1e-6
                ) -> PCAPrior | None:
    """A prior from a spec: ``"shapes"``, a T x m training animation, or None/"none"."""
    if source is None or (isinstance(source, str) and source == "none"):
        return None
    if isinstance(source, str):
        if source != "shapes":
            raise ValueError(f"unknown prior source {source!r} (use 'shapes', 'none' or a weight animation)")
        return PCAPrior.from_shapes(basis, threshold)
    return PCAPrior.from_animation(basis, source, threshold)
