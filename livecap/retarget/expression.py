"""Expression transfer: ARKit weights -> the ICT face -> its marker sites as virtual markers -> any rig.

A rig whose shapes are not ARKit's (the MakeHuman head's FACS-like units) cannot take the curves by
name, and a mapping file guesses one unit per curve. Here the curves drive a rig that has ARKit-like
shapes (ICT-FaceKit, ``../shared/realdata/ict-face``); its marker sites are read off the deformed
face, and the target rig is solved from those virtual markers as from a capture: the ICT face's
neutral markers calibrate the target (rigid alignment and proportion warp, Seol et al. 2012 §3.1-3.2,
livecap.calibration.profile.calibrate), and every frame the displacements go to a solver mode's ``step``.
The virtual face has no head motion (the app sends the head separately), so no stabilisation is needed:
the displacements are rotated into the rig's frame once.

Marker sites on the target: the rig's own markers.json when its labels are the ICT face's (e.g. what
``livecap rig transfer --generic ICT --target NEW.obj`` wrote), else the ICT sites bound to the
target's surface by :func:`livecap.transfer.bind.bind_capture` (similarity ICP; sites that end off its
skin are left out).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livecap.calibration.profile import Profile, calibrate
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.core.take import Take
from livecap.modes.registry import build_solver
from livecap.retarget.by_name import ByName
from solvers.rigid import kabsch


@dataclass(frozen=True)
class TransferSettings:
    """How the target is solved from the virtual markers."""

    # per-frame bounded QP (Curio et al. 2006 §2.3): the virtual markers are noiseless and all seen, so the
    # noise-robust modes' filters would only add lag; the ridge keeps units the markers barely see at rest
    mode: str = "qp"
    ridge: float = 10.0  # mm^2 per unit weight^2; the best of 0-100 on MakeHuman (docs/iphone.md, "Retargeting")
    warp: str = "rbf"  # proportion warp of the calibration (livecap.calibration.profile.fit_warp)


def _select(layout: MarkerLayout, labels: list[str]) -> MarkerLayout:
    idx = [layout.labels.index(lab) for lab in labels]
    return MarkerLayout(list(labels), layout.vertices[idx], layout.barycentric[idx], layout.stable[idx], layout.units)


def bind_sites(via: Rig, via_layout: MarkerLayout, target: Rig) -> MarkerLayout:
    """The via face's marker sites bound to ``target``'s surface (those that land on it), stable flags kept."""
    from livecap.transfer.bind import bind_capture

    sites = via_layout.marker_rig(via).neutral
    frames = np.repeat(sites[None], 40, 0)
    take = Take(list(via_layout.labels), frames, np.ones(frames.shape[:2], bool), 60.0)
    layout = bind_capture(take, target, span=(0, 30)).layout(target)
    stable = dict(zip(via_layout.labels, via_layout.stable, strict=True))
    layout.stable = np.array([stable[lab] for lab in layout.labels])
    return layout


class ExpressionTransfer:
    """Prepared once (calibration, solver); :meth:`step` turns 52 ARKit weights into the target's weights."""

    def __init__(self, via: Rig, via_layout: MarkerLayout, target: Rig, target_layout: MarkerLayout | None = None,
                 settings: TransferSettings | None = None) -> None:
        self.settings = s = settings or TransferSettings()
        self.via = ByName(via, where="the transfer's ICT rig")
        if target_layout is None or not set(target_layout.labels) & set(via_layout.labels):
            target_layout = bind_sites(via, via_layout, target)
        labels = [lab for lab in target_layout.labels if lab in via_layout.labels]
        if len(labels) < 8:
            raise ValueError(f"only {len(labels)} of the ICT face's marker sites land on the target rig")
        self.layout = _select(target_layout, labels)
        self._sites = _select(via_layout, labels).marker_rig(via)
        self._flat = np.ascontiguousarray(self._sites.deltas.reshape(via.n_shapes, -1).T)  # 3n x m_via
        self._linear = self._sites.is_linear
        neutral = self._sites.neutral
        self.profile: Profile = calibrate(target, self.layout, neutral, warp=s.warp)
        R, _ = kabsch(neutral, self.profile.source_neutral)
        self._R = np.ascontiguousarray(R)
        self.solver = build_solver(s.mode, self.profile, {"ridge": s.ridge})
        self._valid = np.ones(len(labels), bool)
        self.names = list(target.names)
        if hasattr(self.solver, "reset"):  # its compiled kernels load here, not on the stream's first packets
            self.step(np.zeros(52))
            self.solver.reset()

    def virtual_markers(self, arkit: np.ndarray) -> np.ndarray:
        """n x 3 displacements of the virtual markers from their neutral, in the target rig's frame."""
        w = self.via.step(np.asarray(arkit, dtype=float))
        if self._linear:
            d = (self._flat @ w).reshape(-1, 3)
        else:
            d = self._sites.evaluate(w) - self._sites.neutral
        return d @ self._R.T

    def step(self, arkit: np.ndarray) -> np.ndarray:
        return np.array(self.solver.step(self.virtual_markers(arkit), self._valid), dtype=float)  # a solver may reuse

    def apply(self, arkit: np.ndarray) -> np.ndarray:
        """T x 52 -> T x m, frame by frame (the solver's state carries over, as live)."""
        return np.array([self.step(a) for a in np.asarray(arkit, dtype=float)]).reshape(-1, len(self.names))
