"""ARKit weights onto a rig's shapes by name, or by a mapping file: one matrix, clipped to the rig's limits."""

from __future__ import annotations

import numpy as np

from livecap.core.names import arkit_to_rig
from livecap.core.rig import Rig


class ByName:
    """``w = clip(A @ arkit)`` with ``A`` from :func:`~livecap.core.names.arkit_to_rig`."""

    def __init__(self, rig: Rig, mapping: dict | None = None, where: str = "rig") -> None:
        self.names = list(rig.names)
        self.matrix = np.ascontiguousarray(arkit_to_rig(self.names, mapping))
        if not self.matrix.any():
            raise ValueError(f"{where}: none of its {len(self.names)} shapes takes an ARKit name "
                             "(give a mapping file, --map, or --transfer)")
        self.lower, self.upper = rig.lower.copy(), rig.upper.copy()
        self._out = np.empty(len(self.names))

    @property
    def driven(self) -> int:
        """How many of the rig's shapes some ARKit curve drives."""
        return int(self.matrix.any(1).sum())

    def step(self, arkit: np.ndarray) -> np.ndarray:
        """One frame's weights (a view of a buffer reused every frame: copy to keep it)."""
        np.dot(self.matrix, arkit, out=self._out)
        return np.clip(self._out, self.lower, self.upper, out=self._out)

    def apply(self, arkit: np.ndarray) -> np.ndarray:
        """T x 52 -> T x m."""
        return np.clip(np.asarray(arkit, dtype=float) @ self.matrix.T, self.lower, self.upper)
