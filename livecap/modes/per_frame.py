"""Factories and settings of the per-frame modes (registered in livecap.modes.registry): ``lsq``, ``qp``
and ``rbf``. Each mode's tunables are one frozen dataclass (``LSQSettings``, ``QPSettings``,
``RBFSettings``) built from the options by its ``from_options``; unset (None) options keep the defaults.

Where keys come from: a labelled range-of-motion take and its keys JSON (``livecap rom --rig RIG``
writes both; docs/calibration.md), or explicit key pairs (``livecap.calibration.keys``).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from livecap.calibration.profile import Profile

log = logging.getLogger(__name__)
KEYS_HINT = ("a keys file: the keys JSON that 'livecap rom --rig RIG --out DIR' writes beside its range-of-motion "
             "take, or explicit key pairs (docs/calibration.md)")


def check_keys(mode: str, options: Mapping) -> None:
    """Argument check before any work: the modes that learn from keys need a keys file."""
    if options.get("keys") is None and (mode == "rbf" or (mode == "qp" and options.get("basis") == "actor")):
        what = "mode rbf" if mode == "rbf" else "qp with basis=actor"
        raise ValueError(f"{what} needs key pairs (--keys): {KEYS_HINT}")


def _given(cls, options: Mapping | None) -> dict:
    names = {f.name for f in fields(cls)}
    return {k: v for k, v in (options or {}).items() if v is not None and k in names}


@dataclass(frozen=True)
class LSQSettings:
    """Plain per-frame bounded least squares: the baseline."""

    ridge: float = 0.0  # Tikhonov weight lambda

    @classmethod
    def from_options(cls, options: Mapping | None) -> LSQSettings:
        return cls(**_given(cls, options))


@dataclass(frozen=True)
class QPSettings:
    """Per-frame bounded QP with ridge and temporal terms (Curio et al. 2006 §2.3)."""

    # lambda |w|^2; 0 is Curio's fit. 3 fits real performances better on rigs with fewer shapes than marker
    # coordinates, but at 1000 shapes it frees ~500 weights and costs ~75 ms a frame (docs/performance.md, "qp's ridge")
    ridge: float = 0.0
    temporal: float = 0.0  # gamma |w - w_prev|^2
    basis: str = "rig"  # "rig" (calibrated rig basis) or "actor" (the actor's own, from ``keys``)
    keys: Any = None  # keys file or KeySet: the ROM the actor basis is built from
    uncovered: str = "rig"  # shapes the ROM lacks: "rig" (keep the rig's) or "drop"

    @classmethod
    def from_options(cls, options: Mapping | None) -> QPSettings:
        return cls(**_given(cls, options))


@dataclass(frozen=True)
class RBFSettings:
    """Example-based solve (Pyun et al. 2003 §3–4)."""

    keys: Any = None  # required: keys file or KeySet
    threshold: float = 1e-5  # PCA eigenvalue threshold, relative to the largest
    clip: bool = True  # clip to the rig's limits

    @classmethod
    def from_options(cls, options: Mapping | None) -> RBFSettings:
        return cls(**_given(cls, options))


def _keyset(profile: Profile, keys):
    from livecap.calibration.keys import KeySet, load_keys

    if keys is None:
        return None
    return keys if isinstance(keys, KeySet) else load_keys(keys, profile)


def key_sources(profile: Profile, keys) -> np.ndarray:
    """M x 3n key displacement vectors; markers unseen at a key come from the calibrated rig."""
    pred = (keys.target @ profile.basis.T).reshape(keys.source.shape)
    return np.where(keys.valid[..., None], keys.source, pred).reshape(len(keys.target), -1)


def lsq_mode(profile: Profile, options: Mapping | None = None):
    from solvers.least_squares import BoundedLeastSquares

    s = LSQSettings.from_options(options)
    return BoundedLeastSquares(profile.basis, profile.lower, profile.upper, float(s.ridge))


def qp_mode(profile: Profile, options: Mapping | None = None):
    from solvers.qp import FrameQP

    s = QPSettings.from_options(options)
    if s.basis == "actor":
        from livecap.calibration.actor_basis import actor_basis

        keys = _keyset(profile, s.keys)
        if keys is None:
            raise ValueError(f"qp with basis=actor needs keys (--keys): {KEYS_HINT}")
        profile, report = actor_basis(profile, keys, s.uncovered)
        for line in report.lines():
            log.info(line)
    elif s.basis != "rig":
        raise ValueError(f"unknown basis {s.basis!r} (rig or actor)")
    return FrameQP(profile.basis, profile.lower, profile.upper, ridge=float(s.ridge), temporal=float(s.temporal))


def rbf_mode(profile: Profile, options: Mapping | None = None):
    from solvers.rbf import KeyBlendSolver

    s = RBFSettings.from_options(options)
    keys = _keyset(profile, s.keys)
    if keys is None:
        raise ValueError(f"mode rbf needs key pairs (--keys): {KEYS_HINT}")
    if keys.skipped:
        log.info("keys naming no rig shape (skipped): %s", ", ".join(keys.skipped))
    return KeyBlendSolver(key_sources(profile, keys), keys.target, profile.lower, profile.upper,
                          threshold=float(s.threshold) or 1e-5, clip=bool(s.clip))
