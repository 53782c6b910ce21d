"""The constant blocks of movement matching and their decoupling (Seol et al. 2012 §4, §5, §7.1).

Movement matching with the prior and the Sobolev position term,

    sum_t |B(w_t - w_{t-1}) - (s_t - s_{t-1})|^2 + alpha sum_t prior(w_t)
        + beta sum_t |M(B w_t - s_t)|^2 + ridge sum_t |w_t|^2,

has normal equations (L (x) G + I (x) K) w = r: L is the path Laplacian in time (tridiagonal),
G = B^T B and K = alpha P + beta B^T M^2 B + ridge I are constant m x m blocks. The generalised
eigenproblem G u = g (G + K) u gives U with U^T (G + K) U = I, U^T G U = diag(g),
U^T K U = diag(1 - g); substituting w_t = U y_t splits the mf x mf system into m independent
tridiagonal systems (g_k L + (1 - g_k) I) y_k = (U^T r)_k. Nothing larger than m x m is formed.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from scipy.linalg.lapack import dpttrf

from solvers.prior import PCAPrior


class IllPosedError(ValueError):
    """The objective does not determine the weights (no boundary and no prior/beta/ridge)."""


class MovementBlocks:
    """Constant blocks G, K, their joint diagonalisation U, g, and the data projections.

    ``marker_weights`` is the diagonal of M (per marker, so each marker's three rows get its
    square); ``prior`` a :class:`PCAPrior` used with weight ``alpha``.
    """

    def __init__(self, basis: np.ndarray, *, alpha: float = 0.0, prior: PCAPrior | None = None,
                 beta: float = 0.0, marker_weights: np.ndarray | None = None, ridge: float = 0.0) -> None:
        B = np.ascontiguousarray(basis, dtype=np.float64)
        if B.ndim != 2 or B.shape[0] % 3:
            raise ValueError(f"basis must be 3n x m, got shape {B.shape}")
        self.basis = B
        n3, m = B.shape
        self.alpha, self.beta, self.ridge = float(alpha), float(beta), float(ridge)
        if min(self.alpha, self.beta, self.ridge) < 0:
            raise ValueError("alpha, beta and ridge must be >= 0")
        if self.alpha > 0 and prior is None:
            raise ValueError("alpha > 0 needs a prior")
        self.prior = prior if self.alpha > 0 else None
        mw = np.ones(n3 // 3) if marker_weights is None else np.asarray(marker_weights, dtype=np.float64)
        if mw.shape != (n3 // 3,):
            raise ValueError(f"marker_weights must have one value per marker ({n3 // 3}), got {mw.shape}")
        self.row_weights = np.repeat(mw**2, 3)  # diag(M^2) over the 3n rows
        G = B.T @ B
        K = self.ridge * np.eye(m)
        const = np.zeros(m)
        if self.prior is not None:
            K += self.alpha * self.prior.precision
            const = self.alpha * self.prior.gradient_constant()
        if self.beta > 0:
            K += self.beta * (B.T @ (self.row_weights[:, None] * B))
        self.G, self.K = 0.5 * (G + G.T), 0.5 * (K + K.T)
        N = self.G + self.K
        try:
            g, U = scipy.linalg.eigh(self.G, N)
        except np.linalg.LinAlgError:
            raise IllPosedError("G + K is singular: some weight moves no marker and has no prior, beta or "
                                "ridge term (add a ridge)") from None
        self.g = np.clip(g, 0.0, 1.0)
        self.U = U  # w = U y
        self.UG = U.T @ self.G  # boundary coupling: U^T G w_fixed
        self.const_weights = const  # alpha P w_mean
        self.const = U.T @ const  # projected
        self.Qm = U.T @ B.T  # movement data projection: q_t = U^T B^T s_t
        self.Qb = (U.T @ B.T) * (self.beta * self.row_weights)[None, :] if self.beta > 0 else None
        self.BU = B @ U  # model fit from modal coordinates: B w = BU y
        self.NU = N @ U  # U^-T: back from projected right-hand sides to weight space, r = (U^T r) @ NU^T

    @property
    def n_shapes(self) -> int:
        return self.basis.shape[1]

    def project(self, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Projected data for every frame: q_t = U^T B^T s_t and qb_t = beta U^T B^T M^2 s_t."""
        S = targets.reshape(len(targets), -1)
        return S @ self.Qm.T, (S @ self.Qb.T if self.Qb is not None else None)

    def to_weights(self, y: np.ndarray) -> np.ndarray:
        return y @ self.U.T

    def per_frame(self, targets: np.ndarray) -> np.ndarray:
        """Per-frame minimiser of |B w - s|^2 + the K terms, for T x 3n (or T x n x 3) targets.

        (G + K) w = B^T s + beta B^T M^2 s + alpha P w_mean, and U U^T = (G + K)^-1.
        """
        q, qb = self.project(np.asarray(targets, dtype=np.float64))
        return self.to_weights(q + self.const + (qb if qb is not None else 0.0))


def factor_modes(g: np.ndarray, free: np.ndarray, T: int):
    """LDL^T (LAPACK ``pttrf``) of the m stacked tridiagonal systems (g_k L_ff + (1 - g_k) I).

    L_ff is the path Laplacian of a T-frame take restricted to the ``free`` frames (a free frame
    next to a fixed one keeps that edge in its degree: the fixed value moves to the right-hand
    side, Seol's appendix). Returns None when no frame is free.
    """
    N = len(free)
    if N == 0:
        return None
    deg = (free > 0).astype(np.float64) + (free < T - 1)
    adj = (np.diff(free) == 1).astype(np.float64)
    d = (g[:, None] * deg[None, :] + (1.0 - g)[:, None]).ravel()
    e = np.zeros((len(g), N))
    e[:, :-1] = -g[:, None] * adj[None, :]
    d, e, info = dpttrf(d, e.ravel()[:-1])
    if info != 0:
        raise IllPosedError("movement matching is not determined: a stretch of free frames has no boundary "
                            "frame and no prior/beta/ridge term (fix a frame, or set beta or ridge > 0)")
    return d, e
