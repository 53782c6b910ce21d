"""The bundled demo take, calibrated as ``livecap solve`` would (neutral from its first second,
regularisation selected from the take), with its generator's ground truth: shared by the suites
that measure accuracy on a real take as well as time."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livecap.calibration.profile import Profile

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"
TAKE = RECORDINGS / "demo_take.c3d"


@dataclass
class DemoTake:
    profile: Profile
    targets: np.ndarray  # T x n x 3 stabilised displacements
    valid: np.ndarray  # T x n
    truth: np.ndarray  # T x m ground-truth weights
    names: list[str]


def demo_take() -> DemoTake:
    from livecap.cli.common import load_rig, profile_for
    from livecap.demo import truth_path
    from livecap.demo.performance import GroundTruth
    from livecap.offline.solve import prepare_targets
    from transport.takefile import read_take

    args = argparse.Namespace(rig=str(RECORDINGS / "demo_rig.npz"), markers=None, profile=None, neutral_seconds=1.0)
    rig, layout = load_rig(args)
    take = read_take(TAKE)
    profile = profile_for(args, rig, layout, take)
    sel, targets, _, _ = prepare_targets(take, profile)
    return DemoTake(profile, targets, sel.valid, GroundTruth.load(truth_path(TAKE)).weights, list(rig.names))
