"""An actor-space marker basis from a range-of-motion take (Curio et al. 2006 §2.3).

Curio et al. build "a morph basis ... from the peak frames of each of the basic facial expressions
of the second actor, effectively creating a second morphable model for 72 marker positions that
spans the same basis as used for the dense 3D shape model". The columns are the actor's own marker
motion, so no proportion warp stands between the markers and the basis; weights solved against it
pass to the target rig by shape name (parallel parameterisation, Lewis et al. 2014 §5.3).

Generalised to keys that mix shapes: the basis columns of the shapes the keys touch are the least
squares solution of  key_weights @ B' = key_displacements;  a key that is one shape at weight 1
gives exactly its peak frame (Curio's case). Shapes no key touches keep the calibrated rig basis
(``missing="rig"``) or are switched off (``missing="drop"``: column zero, limits [0, 0]); either
way they are reported.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from livecap.calibration.keys import KeySet
from livecap.calibration.profile import Profile


@dataclass
class ActorBasisReport:
    from_actor: list[str]  # target shapes whose column is the actor's own motion
    no_actor_pose: list[str]  # target shapes the ROM never performed
    unmatched_keys: list[str]  # ROM labels that name no target shape (and give no weights)
    markers_from_rig: int  # basis entries filled from the rig because a marker was never seen

    def lines(self) -> list[str]:
        out = [f"actor basis: {len(self.from_actor)} shapes from the actor's ROM"]
        if self.no_actor_pose:
            out.append(f"target shapes with no actor pose ({len(self.no_actor_pose)}): {', '.join(self.no_actor_pose)}")
        if self.unmatched_keys:
            out.append(f"ROM labels with no target shape: {', '.join(self.unmatched_keys)}")
        if self.markers_from_rig:
            out.append(f"{self.markers_from_rig} marker entries unseen at their key frame: taken from the rig")
        return out


def actor_basis(profile: Profile, keys: KeySet, missing: str = "rig") -> tuple[Profile, ActorBasisReport]:
    """A copy of ``profile`` whose basis comes from the actor's key frames where it can."""
    if missing not in ("rig", "drop"):
        raise ValueError(f"missing must be 'rig' or 'drop', got {missing!r}")
    if list(keys.shape_names) != list(profile.names):
        raise ValueError("keys were built for a different rig (shape names differ)")
    n, m = profile.n_markers, len(profile.names)
    W = np.asarray(keys.target, dtype=np.float64)  # M x m
    covered = np.where(np.any(np.abs(W) > 1e-12, axis=0))[0]
    # Marker entries unseen at a key: take what the calibrated rig basis predicts there.
    rig_pred = (W @ profile.basis.T).reshape(len(W), n, 3)
    S = np.where(keys.valid[..., None], keys.source, rig_pred).reshape(len(W), 3 * n)
    cols = np.linalg.lstsq(W[:, covered], S, rcond=None)[0]  # |covered| x 3n
    basis = profile.basis.copy()
    lower, upper = profile.lower.copy(), profile.upper.copy()
    basis[:, covered] = cols.T
    uncovered = np.setdiff1d(np.arange(m), covered)
    if missing == "drop":
        basis[:, uncovered] = 0.0
        lower[uncovered] = upper[uncovered] = 0.0
    settings = {**profile.settings, "basis": "actor", "actor_shapes": len(covered), "missing": missing}
    out = replace(profile, basis=basis, lower=lower, upper=upper, settings=settings)
    report = ActorBasisReport([profile.names[i] for i in covered], [profile.names[i] for i in uncovered],
                              list(keys.skipped), int((~keys.valid).sum()))
    return out, report
