"""One annotated preview frame from weights, head pose and markers: the unit offscreen and window sinks draw."""

from __future__ import annotations

import numpy as np

from livecap.core.markers import MarkerLayout
from livecap.core.result import SolveResult
from livecap.core.rig import Rig
from viewer.compose import Caption, put_lines, retarget_markers, top_shapes, weight_bars
from viewer.renderer import Renderer
from viewer.scene import Similarity, model_matrix


class Preview:
    """Renderer + the calibration's rig-to-actor similarity + overlays (bars, caption, title).

    ``profile`` (a livecap Profile, optional) supplies the actor's neutral markers and the rig's rest
    sites; without it the head pose is applied in rig units and no source markers are drawn.
    ``follow_head`` (default) drops the head's translation so the camera stays on the face while
    its rotation still shows; calibration puts the stabilised frame on the rig's, so the raw
    translation is where the head is in the capture volume (metres away from the camera).
    """

    def __init__(self, rig: Rig, layout: MarkerLayout | None = None, profile=None, size=(640, 480), ctx=None,
                 samples: int = 0, deformation: str = "gpu", bars: int = 8, follow_head: bool = True) -> None:
        self.rig, self.layout, self.bars, self.follow_head = rig, layout, bars, follow_head
        self.renderer = Renderer(rig, layout, size, ctx=ctx, samples=samples, deformation=deformation)
        self.head = Similarity()
        self.source_neutral = self.rest_sites = None
        if profile is not None and layout is not None:
            if list(profile.labels) != list(layout.labels):
                raise ValueError("profile and marker layout list different markers")
            self.source_neutral = np.asarray(profile.source_neutral, dtype=np.float64)
            self.rest_sites = np.asarray(profile.target_sites, dtype=np.float64)
            self.head = Similarity.fit(self.rest_sites, self.source_neutral)

    def draw(self, weights: np.ndarray, rotation=None, translation=None, markers: np.ndarray | None = None,
             valid: np.ndarray | None = None, caption: Caption | None = None, head: Similarity | None = None,
             reference: np.ndarray | None = None, order: np.ndarray | None = None) -> np.ndarray:
        """BGR frame. ``markers``: stabilised source markers (head frame, mm) in profile order.

        ``head``: the similarity the pose was measured against (default: the profile's); the
        display frame is always the profile's, so panels drawn with different heads line up.
        ``reference``: weights drawn as ticks on the bars (ground truth).
        """
        model = model_matrix(rotation, None if self.follow_head else translation, head or self.head, self.head)
        rig_markers = None
        if markers is not None and self.source_neutral is not None:
            rig_markers = retarget_markers(markers, self.source_neutral, self.rest_sites, self.head)
        img = self.renderer.render(weights, model, rig_markers, valid, show_sites=self.layout is not None)
        if self.bars:
            order = top_shapes(weights, self.bars, reference) if order is None else order
            weight_bars(img, self.rig.names, weights, order, self.rig.upper, reference)
        if caption is not None:
            ov = self.renderer.last_overlay
            put_lines(img, caption.lines(ov.rms_mm if ov is not None and rig_markers is not None else None))
            if caption.title:
                put_lines(img, [caption.title], bottom=False)
        return img

    def draw_result(self, result: SolveResult, title: str = "") -> np.ndarray:
        """Draw one SolveResult as published by a solve loop (live window, replay)."""
        cap = Caption(result.frame, result.timestamp, result.solve_time * 1e3, title)
        return self.draw(result.weights, result.head_rotation, result.head_translation, result.markers,
                         result.valid, cap)
