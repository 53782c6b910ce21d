"""Factories for the per-frame modes (registered in livecap.modes.registry): ``qp`` and ``rbf``.

Options (from the CLI or a session config):

* qp: ``ridge`` (lambda), ``temporal`` (gamma), ``basis`` ("rig" | "actor"), ``keys`` (keys file or
  KeySet; with basis="actor" the ROM the actor basis is built from, Curio et al. 2006 §2.3),
  ``uncovered`` ("rig" | "drop", for shapes the ROM lacks).
* rbf: ``keys`` (required: key pairs, Pyun et al. 2003 §3), ``threshold`` (PCA eigenvalue
  threshold, relative), ``clip`` (clip to the rig's limits, default true).
"""

from __future__ import annotations

import logging

import numpy as np

from livecap.calibration.profile import Profile

log = logging.getLogger(__name__)


def _keyset(profile: Profile, options: dict):
    from livecap.calibration.keys import KeySet, load_keys

    keys = options.get("keys")
    if keys is None:
        return None
    return keys if isinstance(keys, KeySet) else load_keys(keys, profile)


def key_sources(profile: Profile, keys) -> np.ndarray:
    """M x 3n key displacement vectors; markers unseen at a key come from the calibrated rig."""
    pred = (keys.target @ profile.basis.T).reshape(keys.source.shape)
    return np.where(keys.valid[..., None], keys.source, pred).reshape(len(keys.target), -1)


def qp_mode(profile: Profile, options: dict):
    from solvers.qp import FrameQP

    if options.get("basis", "rig") == "actor":
        from livecap.calibration.actor_basis import actor_basis

        keys = _keyset(profile, options)
        if keys is None:
            raise ValueError("qp with basis=actor needs keys (a labelled range-of-motion take: --keys)")
        profile, report = actor_basis(profile, keys, options.get("uncovered", "rig"))
        for line in report.lines():
            log.info(line)
    elif options.get("basis", "rig") != "rig":
        raise ValueError(f"unknown basis {options['basis']!r} (rig or actor)")
    return FrameQP(profile.basis, profile.lower, profile.upper, ridge=float(options.get("ridge") or 0.0),
                   temporal=float(options.get("temporal") or 0.0))


def rbf_mode(profile: Profile, options: dict):
    from solvers.rbf import KeyBlendSolver

    keys = _keyset(profile, options)
    if keys is None:
        raise ValueError("mode rbf needs key pairs (--keys keys.json: a labelled ROM take or explicit keys)")
    if keys.skipped:
        log.info("keys naming no rig shape (skipped): %s", ", ".join(keys.skipped))
    return KeyBlendSolver(key_sources(profile, keys), keys.target, profile.lower, profile.upper,
                          threshold=float(options.get("threshold") or 1e-5), clip=bool(options.get("clip", True)))
