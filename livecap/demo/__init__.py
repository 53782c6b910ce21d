"""The bundled demo: a procedural rig, its markers, and synthetic takes with ground truth."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from livecap.demo.face import demo_rig
from livecap.demo.performance import PerformanceSettings, perform

DEMO_RIG = "demo_rig.npz"
DEMO_MARKERS = "demo_rig.markers.json"
DEMO_TAKE = "demo_take.c3d"
DEMO_NEUTRAL = "demo_neutral.c3d"


def truth_path(take_path: str | Path) -> Path:
    """Ground truth lives next to a take: ``<take>.truth.npz``."""
    p = Path(take_path)
    return p.with_name(p.stem + ".truth.npz")


def generate(out_dir: str | Path, seed: int = 0, settings: PerformanceSettings | None = None) -> list[Path]:
    """Write the demo rig, markers, a neutral take and a performance take (with ground truth)."""
    from transport.takefile import write_take

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rig, layout = demo_rig(seed)
    rig.save(out / DEMO_RIG)
    layout.save(out / DEMO_MARKERS)
    s = settings or PerformanceSettings(seed=seed + 1)
    perf = perform(rig, layout, s)
    write_take(perf.take, out / DEMO_TAKE)
    perf.save_truth(truth_path(out / DEMO_TAKE))
    neutral_settings = replace(s, seconds=2.0, neutral_start=2.0, neutral_end=0.0, beyond_limits=False,
                               stable_dropout=0.0, occlusion=0.0, seed=s.seed + 100)
    neutral = perform(rig, layout, neutral_settings)
    write_take(neutral.take, out / DEMO_NEUTRAL)
    return [out / DEMO_RIG, out / DEMO_MARKERS, out / DEMO_TAKE, truth_path(out / DEMO_TAKE), out / DEMO_NEUTRAL]
