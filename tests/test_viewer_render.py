"""Real rendering through EGL (Mesa llvmpipe): GPU deformation, shading, overlay, head pose."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from viewer.renderer import SITE_COLOUR, SOURCE_COLOUR, Renderer, field_coefficients
from viewer.scene import pose_matrix, vertex_normals


@pytest.fixture(scope="module")
def demo_renderer(demo):
    rig, layout = demo
    return Renderer(rig, layout, size=(320, 240))


def _gpu_matches_evaluate(renderer, rig, w) -> float:
    """Max GPU-vs-float64 vertex error as a fraction of the face's size."""
    renderer.deform(w)
    got = renderer.read_positions().astype(np.float64)
    want = rig.evaluate(w)
    extent = float(np.ptp(rig.neutral, axis=0).max())
    return float(np.abs(got - want).max() / extent)


def test_field_coefficients_reproduce_evaluate(demo):
    rig, _ = demo
    rng = np.random.default_rng(3)
    w = rng.uniform(-0.2, 1.2, rig.n_shapes)
    c = field_coefficients(rig, w)
    fields = np.concatenate([rig.deltas, [i.residual for i in rig.inbetweens], [c_.delta for c_ in rig.correctives]])
    np.testing.assert_allclose(rig.neutral + np.einsum("f,fvc->vc", c, fields), rig.evaluate(w), atol=1e-9)
    assert len(rig.inbetweens) and len(rig.correctives)  # the demo exercises both nonlinear parts


@settings(max_examples=15, deadline=None)
@given(st.lists(st.floats(-0.3, 1.3), min_size=43, max_size=43), st.floats(0.0, 1.0))
def test_gpu_deformation_equals_rig_evaluate_demo(demo, demo_renderer, ws, sparsity):
    rig, _ = demo
    w = np.array(ws[: rig.n_shapes])
    w[np.arange(rig.n_shapes) / rig.n_shapes < sparsity] = 0.0  # mixes dense and sparse weight vectors
    # float32 on the GPU: 1e-5 of the face size is ~2 mm * 1e-3, a few float32 ulps of the coordinates
    assert _gpu_matches_evaluate(demo_renderer, rig, w) < 1e-5


def test_gpu_deformation_hits_inbetweens_and_correctives(demo, demo_renderer):
    rig, _ = demo
    for ib in rig.inbetweens:  # exactly at the in-between sculpt, where the hat peaks
        w = np.zeros(rig.n_shapes)
        w[ib.shape] = ib.weight
        assert _gpu_matches_evaluate(demo_renderer, rig, w) < 1e-5
    for co in rig.correctives:
        w = np.zeros(rig.n_shapes)
        w[list(co.shapes)] = 1.0
        assert _gpu_matches_evaluate(demo_renderer, rig, w) < 1e-5
        assert np.abs(co.delta).max() > 0.1  # the corrective really moves the face


def test_gpu_normals_follow_the_deformed_surface(demo, demo_renderer):
    rig, _ = demo
    w = np.zeros(rig.n_shapes)
    w[rig.index("jawOpen")] = 1.0
    demo_renderer.deform(w)
    got = demo_renderer.read_normals()
    want = vertex_normals(rig.evaluate(w), rig.triangles)
    assert np.abs(got - want).max() < 1e-4
    rest = vertex_normals(rig.neutral, rig.triangles)
    assert np.abs(want - rest).max() > 0.1  # the neutral's normals would be wrong here


def test_gpu_deformation_equals_rig_evaluate_ict(ict):
    rig, layout = ict  # ICT-FaceKit: quads triangulated on load
    r = Renderer(rig, layout, size=(160, 120))
    rng = np.random.default_rng(0)
    for w in (np.zeros(rig.n_shapes), rng.uniform(0, 1, rig.n_shapes), np.eye(rig.n_shapes)[rig.index("jawOpen")]):
        assert _gpu_matches_evaluate(r, rig, w) < 1e-5
    r.release()


def test_jaw_open_changes_the_mouth_and_nothing_else(demo):
    rig, _ = demo
    r = Renderer(rig, None, size=(320, 240))
    w = np.zeros(rig.n_shapes)
    neutral = r.render(w).astype(int)
    w[rig.index("jawOpen")] = 1.0
    jaw = r.render(w).astype(int)
    moving = np.linalg.norm(rig.deltas[rig.index("jawOpen")], axis=1) > 1e-6
    px = np.concatenate([r.project(rig.neutral[moving]), r.project(rig.evaluate(w)[moving])])
    # the region the jaw's vertices cover at rest and open, plus a margin for the shading of their one-ring
    lo, hi = px.min(0) - 6, px.max(0) + 6
    ys, xs = np.mgrid[0:240, 0:320]
    region = (xs >= lo[0]) & (xs <= hi[0]) & (ys >= lo[1]) & (ys <= hi[1])
    diff = np.abs(neutral - jaw).max(axis=2)
    assert (diff[region] > 20).sum() > 200  # the mouth visibly opens
    assert diff[~region].max() <= 2  # the rest of the face is the same picture
    assert (diff[~region] == 0).mean() > 0.99
    face = np.abs(neutral - np.array([r.background[::-1]]) * 255).max(axis=2) > 10
    assert face.mean() > 0.1 and face[~region].sum() > 1000  # a face, not an empty frame
    shade = neutral[face].mean(axis=1)
    assert shade.std() > 15  # lit: shading varies across the face (not a flat blob)


def test_marker_overlay_lands_where_the_projection_says(demo):
    rig, layout = demo
    r = Renderer(rig, layout, size=(320, 240))
    w = np.zeros(rig.n_shapes)
    w[rig.index("mouthSmileLeft")] = 0.8
    model = pose_matrix([0.0, np.sin(0.15), 0.0, np.cos(0.15)], [12.0, -5.0, 8.0])  # ~17 degrees yaw
    sites = r.sites(w)
    markers = sites + [0.0, 9.0, 0.0]  # sources offset 9 mm above their sites
    valid = np.ones(layout.n_markers, bool)
    valid[::5] = False
    img = r.render(w, model, markers, valid).astype(int)
    bgr_src = np.array(SOURCE_COLOUR[::-1]) * 255
    bgr_site = np.array(SITE_COLOUR[::-1]) * 255
    disp_src = markers @ model[:3, :3].T + model[:3, 3]
    disp_site = sites @ model[:3, :3].T + model[:3, 3]

    def colour_at(points):
        px = np.floor(r.project(points)).astype(int)
        return img[px[:, 1], px[:, 0]]

    src_px = colour_at(disp_src[valid])
    assert np.abs(src_px - bgr_src).max(axis=1).max() < 40  # every visible source marker is drawn there
    site_px = colour_at(disp_site)
    assert (np.abs(site_px - bgr_site).max(axis=1) < 40).mean() > 0.9  # sites (a few hidden under sources)
    missing = colour_at(disp_src[~valid])
    assert (np.abs(missing - bgr_src).max(axis=1) > 80).all()  # invalid markers are not drawn
    assert r.last_overlay is not None and abs(r.last_overlay.rms_mm - 9.0) < 1e-6
