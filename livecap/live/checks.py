"""Start-of-session checks: refuse a session that could only solve badly, with one line that
names the files (issue 17: a profile sharing no labels with the take gave all-zero weights)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from livecap.calibration.profile import Profile, rig_fingerprint
from livecap.core.rig import Rig

MIN_STABLE = 3  # the head stabiliser's rigid fit needs three stable markers


def check_overlap(stream_labels: Sequence[str], labels: Sequence[str], stable: np.ndarray, stream: str,
                  against: str) -> None:
    """The stream must carry at least :data:`MIN_STABLE` of the session's stable markers."""
    have = set(stream_labels)
    shared = [lab for lab in labels if lab in have]
    shared_stable = [lab for lab, s in zip(labels, stable, strict=True) if s and lab in have]
    if len(shared_stable) < MIN_STABLE:
        raise ValueError(f"{stream}: shares {len(shared)} of {len(labels)} marker labels with {against} "
                         f"({len(shared_stable)} of the stable ones, {MIN_STABLE} needed): wrong take or profile?")


def check_profile_rig(profile: Profile, rig: Rig, profile_path: str, rig_path: str) -> None:
    """A profile calibrated against another rig would solve silently badly: refuse it."""
    if list(profile.names) != list(rig.names):
        raise ValueError(f"{profile_path}: its {len(profile.names)} shape names are not those of the rig "
                         f"{rig_path} ({rig.n_shapes} shapes): calibrated for another rig")
    stored = profile.settings.get("rig_fingerprint")
    if stored is not None and stored != rig_fingerprint(rig):
        raise ValueError(f"{profile_path}: calibrated against rig {stored}, but --rig {rig_path} is "
                         f"{rig_fingerprint(rig)}: recalibrate, or give the rig it was made for")
