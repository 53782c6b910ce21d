"""Scale-proportion matching by an RBF warp (Seol et al. 2012 §3.2).

    d(x) = sum_i w_i |x - c_i| + q(x),     q affine,

fitted so the target rig's neutral marker sites (the centres c_i) land exactly on the actor's
neutral markers. The kernel |x - c| minimises the bending energy of the deformation in 3D (the
biharmonic spline); with the affine term the warp reproduces any affine map exactly, so a
similarity between rig and actor is a special case. Applied to every shape's marker sites, it
gives the marker-space basis B in the actor's proportions (Seol's b*_ij = d(b_ij)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livecap.core.rig import Corrective, InBetween, Rig


class WarpError(ValueError):
    """A warp that cannot be fitted (too few or coplanar centres)."""


@dataclass
class ProportionWarp:
    """d(x) = W^T phi(x) + A^T [x, 1] on normalised inputs (x - mu) / scale (for conditioning)."""

    centres: np.ndarray  # n x 3, target-neutral marker sites (mm)
    weights: np.ndarray  # n x 3 RBF weights
    affine: np.ndarray  # 4 x 3: rows x, y, z, 1 of the linear polynomial
    mu: np.ndarray  # 3, normalisation offset
    scale: float  # normalisation scale (mm)

    @classmethod
    def fit(cls, centres: np.ndarray, targets: np.ndarray, smoothing: float = 0.0) -> ProportionWarp:
        """Solve [[K + smoothing I, P], [P^T, 0]] [W; A] = [targets; 0] (Seol §3.2).

        ``smoothing`` = 0 interpolates exactly; > 0 (mm per unit weight, in normalised units)
        trades exactness for smoothness when the neutral is noisy.
        """
        c = np.asarray(centres, dtype=np.float64)
        y = np.asarray(targets, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 3 or y.shape != c.shape:
            raise WarpError(f"centres and targets must both be n x 3, got {c.shape} and {y.shape}")
        n = len(c)
        mu = c.mean(0)
        scale = float(np.sqrt(np.mean(np.sum((c - mu) ** 2, axis=1)))) or 1.0
        cn = (c - mu) / scale
        P = np.hstack([cn, np.ones((n, 1))])
        if n < 4 or np.linalg.matrix_rank(P, tol=1e-8 * n) < 4:
            raise WarpError(f"the RBF warp needs at least 4 non-coplanar marker sites (got {n})")
        K = np.linalg.norm(cn[:, None, :] - cn[None, :, :], axis=2) + smoothing * np.eye(n)
        M = np.zeros((n + 4, n + 4))
        M[:n, :n] = K
        M[:n, n:] = P
        M[n:, :n] = P.T
        rhs = np.zeros((n + 4, 3))
        rhs[:n] = y
        try:
            sol = np.linalg.solve(M, rhs)
        except np.linalg.LinAlgError as exc:
            raise WarpError(f"RBF warp system is singular ({exc}); are two marker sites identical?") from None
        return cls(c, sol[:n], sol[n:], mu, scale)

    @classmethod
    def from_affine(cls, matrix: np.ndarray, offset: np.ndarray, centres: np.ndarray) -> ProportionWarp:
        """The affine map x -> matrix @ x + offset as a warp with no radial part (e.g. a similarity)."""
        c = np.asarray(centres, dtype=np.float64)
        mu = c.mean(0)
        scale = float(np.sqrt(np.mean(np.sum((c - mu) ** 2, axis=1)))) or 1.0
        M = np.asarray(matrix, dtype=np.float64)
        A = np.vstack([scale * M.T, (M @ mu + np.asarray(offset, dtype=np.float64))[None]])
        return cls(c, np.zeros_like(c), A, mu, scale)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Warp points (..., 3)."""
        x = np.asarray(x, dtype=np.float64)
        xn = (x - self.mu) / self.scale
        cn = (self.centres - self.mu) / self.scale
        phi = np.linalg.norm(xn[..., None, :] - cn, axis=-1)  # (..., n)
        return phi @ self.weights + xn @ self.affine[:3] + self.affine[3]

    @property
    def linear(self) -> np.ndarray:
        """The 3 x 3 linear part of the affine term, in mm per mm."""
        return self.affine[:3].T / self.scale

    @property
    def mean_scale(self) -> float:
        """Cube root of det(linear part): the warp's overall size change."""
        return float(np.cbrt(np.linalg.det(self.linear)))

    def to_arrays(self, prefix: str = "warp_") -> dict[str, np.ndarray]:
        return {f"{prefix}centres": self.centres, f"{prefix}weights": self.weights, f"{prefix}affine": self.affine,
                f"{prefix}mu": self.mu, f"{prefix}scale": np.array(self.scale)}

    @classmethod
    def from_arrays(cls, z, prefix: str = "warp_") -> ProportionWarp:
        return cls(np.asarray(z[f"{prefix}centres"], float), np.asarray(z[f"{prefix}weights"], float),
                   np.asarray(z[f"{prefix}affine"], float), np.asarray(z[f"{prefix}mu"], float),
                   float(z[f"{prefix}scale"]))


def warp_rig(sites: Rig, warp) -> Rig:
    """The marker-site rig with every sculpt warped: Seol's b*_ij = d(b_ij) (§3.2).

    Each whole-face sculpt (shape at weight 1, in-between at its weight, combination at its
    members' weights 1) is warped and re-expressed in the delta form, so the warped rig evaluated
    at a sculpt's weights gives exactly the warped sculpt; in-betweens and correctives stay
    nonlinear. ``warp`` is any callable on (..., 3) points.
    """
    neutral = warp(sites.neutral)
    deltas = warp(sites.neutral + sites.deltas) - neutral
    inbetweens = []
    for ib in sites.inbetweens:
        face = sites.neutral + ib.weight * sites.deltas[ib.shape] + ib.residual
        residual = warp(face) - neutral - ib.weight * deltas[ib.shape]
        inbetweens.append(InBetween(ib.shape, ib.weight, ib.left, ib.right, residual))
    out = Rig(neutral, np.zeros((0, 3), np.int64), list(sites.names), deltas, sites.lower.copy(),
              sites.upper.copy(), inbetweens, [])
    # Correctives in order of size: a combination's sculpt includes every smaller one inside it.
    fixed: dict[int, Corrective] = {}
    for i in sorted(range(len(sites.correctives)), key=lambda j: len(sites.correctives[j].shapes)):
        c = sites.correctives[i]
        w = np.zeros(sites.n_shapes)
        w[list(c.shapes)] = 1.0
        sculpt = warp(sites.evaluate(w))
        out.correctives = [fixed[j] for j in sorted(fixed)]
        fixed[i] = Corrective(c.shapes, sculpt - out.evaluate(w))
    out.correctives = [fixed[j] for j in range(len(sites.correctives))]
    return out
