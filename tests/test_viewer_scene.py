"""Geometry of the preview (no GL): poses, similarities, projection, CPU normals, overlay maths."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from viewer.compose import retarget_markers, top_shapes
from viewer.cpu import CpuDeformer
from viewer.scene import Camera, Similarity, model_matrix, pose_matrix, project, quat_matrix, transform, vertex_normals

quats = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)
vecs = st.lists(st.floats(-100, 100), min_size=3, max_size=3)


@given(quats)
def test_quat_matrix_matches_scipy(q):
    np.testing.assert_allclose(quat_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)


@settings(max_examples=50)
@given(quats, vecs, st.floats(0.5, 2.0), quats, vecs)
def test_model_matrix_moves_the_rig_like_the_pose_moves_the_actor(q, t, s, qs, ts):
    """display^-1 . Pose . head: rig points posed in the display frame land where the actor's head put them."""
    head = Similarity(s, Rotation.from_quat(qs).as_matrix(), np.array(ts))
    pts = np.random.default_rng(0).normal(size=(5, 3)) * 50
    actor_raw = transform(pose_matrix(q, t), transform(head.matrix(), pts))
    shown = transform(model_matrix(q, t, head), pts)
    np.testing.assert_allclose(transform(head.matrix(), shown), actor_raw, atol=1e-8)
    np.testing.assert_allclose(model_matrix(None, None, head), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(head.inverse() @ head.matrix(), np.eye(4), atol=1e-12)


def test_similarity_fit_recovers_scale_and_displacements():
    rng = np.random.default_rng(1)
    rig_pts = rng.normal(size=(20, 3)) * 40
    R = Rotation.from_euler("xyz", [10, -20, 5], degrees=True).as_matrix()
    head = Similarity(1.1, R, np.array([3.0, 400.0, -20.0]))
    actor = transform(head.matrix(), rig_pts)
    fit = Similarity.fit(rig_pts, actor)
    assert fit.scale == pytest.approx(1.1)
    moved = actor + rng.normal(size=actor.shape)  # actor displacement from neutral
    retargeted = retarget_markers(moved, actor, rig_pts, fit)
    np.testing.assert_allclose(transform(head.matrix(), retargeted), moved, atol=1e-8)


def test_projection_centres_the_framed_points():
    pts = np.random.default_rng(2).uniform(-80, 80, (100, 3)) + [5, 600, 30]
    cam = Camera.frame(pts, 4 / 3)
    px = project(cam.view_projection(4 / 3), pts, (640, 480))
    assert (px >= 0).all() and (px[:, 0] <= 640).all() and (px[:, 1] <= 480).all()
    centre = project(cam.view_projection(4 / 3), cam.target[None], (640, 480))[0]
    np.testing.assert_allclose(centre, [320, 240], atol=1e-9)
    up = project(cam.view_projection(4 / 3), cam.target[None] + [0, 10, 0], (640, 480))[0]
    assert up[1] < 240  # +y is up on screen


def test_cpu_deformer_matches_reference_normals(demo):
    rig, _ = demo
    w = np.zeros(rig.n_shapes)
    w[rig.index("jawOpen")] = 0.7
    pos, nrm = CpuDeformer(rig)(w)
    np.testing.assert_allclose(pos, rig.evaluate(w), atol=1e-4)
    np.testing.assert_allclose(nrm, vertex_normals(rig.evaluate(w), rig.triangles), atol=1e-6)


def test_top_shapes_orders_by_either_set():
    assert list(top_shapes(np.array([0.1, 0.9, 0.0, 0.5]), 2)) == [1, 3]
    assert list(top_shapes(np.array([0.1, 0.2, 0.0]), 2, also=np.array([0.0, 0.0, 0.8]))) == [2, 1]


def test_weight_bar_labels_are_whole():
    """Issue 21 finding 7: the longest ARKit names (19 letters) fit their column, also in a small frame."""
    import cv2
    import numpy as np

    from viewer.compose import bar_label_layout, weight_bars

    names = ["mouthLowerDownRight", "jawOpen", "eyeBlinkLeft"]
    for width, k in ((640, 1.0), (320, 0.5)):
        fs, name_w = bar_label_layout(names, width, k)
        assert all(cv2.getTextSize(n, cv2.FONT_HERSHEY_SIMPLEX, fs, 1)[0][0] <= name_w for n in names)
        assert name_w <= 0.4 * width + 6 * k
    img = np.zeros((480, 640, 3), np.uint8)
    weight_bars(img, names, np.array([0.5, 1.0, 0.2]), np.arange(3))
    assert img.any()
