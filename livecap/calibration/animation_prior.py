"""A Gaussian prior on a rig's weights learned from real animation (Lewis et al. 2014 §7.8-7.9).

Live Link Face performances are mapped onto the rig's shapes (livecap.core.names.arkit_to_rig)
and their frames give a mean and a full covariance, and the covariance's principal axes give the
PCA subspace (Seol et al. 2012 §5 build theirs from the rig's animation the same way). Shapes the
curves never drive get a variance floor so the covariance is invertible.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

VARIANCE_FLOOR = 1e-4  # (0.01)^2: a shape no curve moves may still move a little


@dataclass(frozen=True)
class AnimationPrior:
    names: tuple[str, ...]
    mean: np.ndarray  # m
    cov: np.ndarray  # m x m
    frames: int
    sources: tuple[str, ...]

    def pca(self, energy: float = 0.99) -> tuple[np.ndarray, np.ndarray]:
        """Principal axes (m x k) and variances keeping ``energy`` of the total variance."""
        var, axes = np.linalg.eigh(self.cov)
        var, axes = var[::-1], axes[:, ::-1]
        k = int(np.searchsorted(np.cumsum(var) / var.sum(), energy) + 1)
        return axes[:, :k], var[:k]

    def root_precision(self) -> np.ndarray:
        """``L`` with ``L.T @ L`` = the inverse covariance (rows = whitened prior residuals)."""
        var, axes = np.linalg.eigh(self.cov)
        return (axes / np.sqrt(np.maximum(var, VARIANCE_FLOOR))).T

    def check(self, names: Sequence[str]) -> None:
        """Refuse a prior over other shapes, or one whose covariance is not positive definite."""
        if list(self.names) != list(names):
            raise ValueError("animation prior was built for another rig's shapes (livecap prior build --rig)")
        m = len(self.names)
        if np.shape(self.mean) != (m,) or np.shape(self.cov) != (m, m):
            raise ValueError(f"animation prior mean {np.shape(self.mean)} / covariance {np.shape(self.cov)} "
                             f"do not fit {m} shapes")
        if not (np.isfinite(self.mean).all() and np.isfinite(self.cov).all()):
            raise ValueError("animation prior holds NaN or infinite values")
        if np.linalg.eigvalsh(self.cov)[0] <= 0:
            raise ValueError("animation prior covariance is not positive definite")

    def to_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        return {f"{prefix}names": np.array(self.names), f"{prefix}mean": self.mean, f"{prefix}cov": self.cov,
                f"{prefix}frames": np.array(self.frames), f"{prefix}sources": np.array(self.sources)}

    @classmethod
    def from_arrays(cls, z: Mapping[str, np.ndarray], prefix: str = "") -> AnimationPrior:
        return cls(tuple(str(n) for n in z[f"{prefix}names"]), np.asarray(z[f"{prefix}mean"], float),
                   np.asarray(z[f"{prefix}cov"], float), int(z[f"{prefix}frames"]),
                   tuple(str(s) for s in z[f"{prefix}sources"]))

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, **self.to_arrays())

    @classmethod
    def load(cls, path: str | Path) -> AnimationPrior:
        try:
            return cls.from_arrays(np.load(path, allow_pickle=False))
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise ValueError(f"{path}: not an animation prior ({exc})") from None


def prior_from_spec(spec, stored: AnimationPrior | None):
    """What a ``prior`` option names, for the modes that read animation priors: 'profile' is the prior
    ``calibrate --prior`` stored (an error when there is none), a .npz path is loaded; anything else is
    returned as it is, for the mode to interpret."""
    if isinstance(spec, str | Path):
        if str(spec) == "profile":
            if stored is None:
                raise ValueError("prior 'profile': the profile carries no animation prior (livecap calibrate --prior)")
            return stored
        if str(spec).endswith(".npz"):
            return AnimationPrior.load(spec)
    return spec


def build_prior(curves: Sequence[str | Path], names: Sequence[str], lower: np.ndarray, upper: np.ndarray,
                mapping: dict | None = None, rate: float = 60.0) -> AnimationPrior:
    """Mean and full covariance of the curves' frames, mapped onto ``names`` and clipped to the limits."""
    from livecap.core.names import arkit_to_rig  # here, not above: every profile load imports this module
    from transport.llf_csv import read_llf_csv

    A = arkit_to_rig(list(names), mapping)
    W = np.concatenate([np.clip(read_llf_csv(c).resample(rate)[0] @ A.T, lower, upper) for c in curves])
    cov = np.cov(W, rowvar=False) + VARIANCE_FLOOR * np.eye(len(names))
    return AnimationPrior(tuple(names), W.mean(0), cov, len(W), tuple(Path(c).name for c in curves))
