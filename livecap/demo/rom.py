"""A range-of-motion (ROM) take: the actor performs every shape in turn, with labelled frame ranges.

This is how Curio et al. 2006 §2.1 recorded their actor ("basic facial actions ... the peak frame
with maximum amplitude of the facial action was identified for each expression") and what the
actor basis and the RBF keys are built from. Each shape rises to full weight, holds, and returns
to neutral; the labelled range covers the whole action, so the peak has to be found, not read off.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from livecap.calibration.keys import KeySpec, write_key_file
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.demo.performance import Performance, PerformanceSettings, perform

DEMO_ROM = "demo_rom.c3d"
DEMO_ROM_KEYS = "demo_rom.keys.json"


def rom_weights(rig: Rig, rate: float, neutral: float = 1.0, ramp: float = 0.25, hold: float = 0.3,
                gap: float = 0.15, shapes: list[str] | None = None) -> tuple[np.ndarray, list[KeySpec]]:
    """T x m weight curves performing each shape alone, and the labelled (inclusive) frame ranges."""
    names = list(shapes if shapes is not None else rig.names)
    n_ramp, n_hold, n_gap = (max(1, int(round(x * rate))) for x in (ramp, hold, gap))
    per = 2 * n_ramp + n_hold + n_gap
    first = int(round(neutral * rate))
    W = np.zeros((first + per * len(names) + first, rig.n_shapes))
    up = 0.5 - 0.5 * np.cos(np.linspace(0, np.pi, n_ramp))
    profile = np.concatenate([up, np.ones(n_hold), up[::-1]])
    specs = []
    for i, name in enumerate(names):
        k = rig.index(name)
        start = first + i * per
        W[start:start + len(profile), k] = min(1.0, float(rig.upper[k])) * profile
        specs.append(KeySpec(name, start=start, end=start + len(profile) - 1))
    return W, specs


def rom_take(rig: Rig, layout: MarkerLayout, settings: PerformanceSettings | None = None,
             shapes: list[str] | None = None) -> tuple[Performance, list[KeySpec]]:
    """A ROM performance by the same actor (``settings.actor_seed``) as the demo take."""
    s = replace(settings or PerformanceSettings(), beyond_limits=False, stable_dropout=0.0)
    W, specs = rom_weights(rig, s.rate, shapes=shapes)
    return perform(rig, layout, s, weights=W), specs


def generate_rom(out_dir: str | Path, rig: Rig, layout: MarkerLayout,
                 settings: PerformanceSettings | None = None, name: str = "demo_rom") -> list[Path]:
    """Write ``<name>.c3d`` (its first second neutral), its ground truth and ``<name>.keys.json``
    (labelled ranges)."""
    from livecap.demo import truth_path
    from transport.takefile import write_take

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    perf, specs = rom_take(rig, layout, settings)
    take, keys = out / f"{name}.c3d", out / f"{name}.keys.json"
    write_take(perf.take, take)
    perf.save_truth(truth_path(take))
    write_key_file(keys, specs, take=take.name)
    return [take, truth_path(take), keys]
