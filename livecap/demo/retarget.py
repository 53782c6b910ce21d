"""A retargeting scenario like Seol et al. 2012 §7 (Figs. 9-11), built from the project's generators.

Seol et al. retarget a source face's motion onto *other* characters (33, 50 and 18 blendshapes)
that cannot reproduce it exactly, through 54 marker correspondences and an RBF warp of
proportions (§3.2). Unconstrained, the target contorts with extreme weights; the constraints
(range, prior) are active. Here:

* source: an actor performing the demo rig ``demo_rig(source_seed)`` (all its shapes), exactly
  as the demo take is made (:func:`livecap.demo.performance.perform`: acting-like curves with
  poses past the rig's limits, a non-affine actor warp, head motion, Gaussian marker noise,
  occlusion bursts);
* target: a *different* character, ``demo_rig(target_seed)`` (other head proportions and shape
  extents) reduced to ``target_shapes`` of its shapes drawn at random with ``subset_seed`` (like
  Seol's smaller character rigs; same marker labels, so correspondences exist);
* calibration: the project's own (neutral from the take's neutral start, rigid frame, RBF warp
  of the target's marker sites onto the actor, Seol §3.2), then head stabilisation and gap
  filling as for any take (:func:`livecap.offline.solve.prepare_targets`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from livecap.calibration.profile import Profile, calibrate, estimate_neutral
from livecap.core.rig import Corrective, InBetween, Rig
from livecap.demo.face import demo_rig
from livecap.demo.performance import PerformanceSettings, perform
from livecap.offline.solve import prepare_targets


@dataclass
class RetargetScenario:
    """Stabilised source displacements in the target's marker space, and the target's basis."""

    targets: np.ndarray  # T x n x 3 mm, displacements from the actor's neutral
    valid: np.ndarray  # T x n
    rate: float
    profile: Profile  # calibration of the reduced target rig onto the actor
    truth: np.ndarray  # T x m_source: the source actor's weights (source rig's shapes)
    info: dict = field(default_factory=dict)

    @property
    def basis(self) -> np.ndarray:
        return self.profile.basis


def reduced_rig(rig: Rig, n_shapes: int, seed: int) -> Rig:
    """``rig`` keeping ``n_shapes`` of its shapes, drawn at random (deterministic in ``seed``).

    In-betweens and correctives survive when all the shapes they belong to do.
    """
    if not 1 <= n_shapes <= rig.n_shapes:
        raise ValueError(f"target shapes must be within 1..{rig.n_shapes}, got {n_shapes}")
    keep = np.sort(np.random.default_rng(seed).choice(rig.n_shapes, n_shapes, replace=False))
    new = {int(k): i for i, k in enumerate(keep)}
    ibs = [InBetween(new[b.shape], b.weight, b.left, b.right, b.residual) for b in rig.inbetweens if b.shape in new]
    cos = [Corrective(tuple(new[s] for s in c.shapes), c.delta) for c in rig.correctives
           if all(s in new for s in c.shapes)]
    return Rig(rig.neutral, rig.triangles, [rig.names[k] for k in keep], rig.deltas[keep], rig.lower[keep],
               rig.upper[keep], ibs, cos)


def retarget_scenario(seconds: float = 20.0, rate: float = 120.0, noise_mm: float = 0.5, occlusion: float = 0.02, *,
                      source_seed: int = 0, target_seed: int = 3, target_shapes: int = 33,
                      subset_seed: int = 11, performance_seed: int = 1,
                      settings: PerformanceSettings | None = None) -> RetargetScenario:
    """Source actor on ``demo_rig(source_seed)`` retargeted to a reduced ``demo_rig(target_seed)``.

    ``settings`` overrides the performance (default: the demo take's, with ``seconds``, ``rate``,
    ``noise_mm``, ``occlusion`` and ``performance_seed``).
    """
    src_rig, src_layout = demo_rig(source_seed)
    s = settings or PerformanceSettings(seconds=seconds, rate=rate, noise_mm=noise_mm, occlusion=occlusion,
                                         seed=performance_seed)
    perf = perform(src_rig, src_layout, s)
    full, layout = demo_rig(target_seed)
    target = reduced_rig(full, target_shapes, subset_seed)
    take = perf.take.select(layout.labels)
    neutral = estimate_neutral(take, layout.stable, max(1, int(round(s.neutral_start * s.rate))))
    profile = calibrate(target, layout, neutral, warp="rbf")
    sel, targets, _, _ = prepare_targets(take, profile)
    info = {"source": f"demo_rig({source_seed}), {src_rig.n_shapes} shapes, performance seed {s.seed}",
            "target": f"demo_rig({target_seed}) reduced to {target.n_shapes} of {full.n_shapes} shapes "
                      f"(subset seed {subset_seed})",
            "target_names": list(target.names), "markers": layout.n_markers, "frames": take.n_frames,
            "rate": s.rate, "noise_mm": s.noise_mm, "occlusion": s.occlusion,
            "warp_fit_rms_mm": profile.settings.get("warp_fit_rms_mm")}
    return RetargetScenario(targets, sel.valid, s.rate, profile, perf.weights, info)
