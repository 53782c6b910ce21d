import json

import numpy as np
import pytest

from livecap.core.markers import LayoutError, MarkerLayout


def test_basis_matches_evaluate(demo):
    rig, layout = demo
    B = layout.basis(rig)
    assert B.shape == (3 * layout.n_markers, rig.n_shapes)
    w = np.zeros(rig.n_shapes)
    w[rig.index("mouthSmileLeft")] = 0.7
    sites = rig.evaluate(w)[layout.vertices[:, 0]]
    np.testing.assert_allclose((B @ w).reshape(-1, 3) + rig.neutral[layout.vertices[:, 0]], sites, atol=1e-9)


def test_marker_rig_keeps_nonlinear_parts(demo):
    rig, layout = demo
    W = np.random.default_rng(3).uniform(0, 1, (4, rig.n_shapes))
    np.testing.assert_allclose(layout.marker_rig(rig).evaluate(W), rig.evaluate(W)[:, layout.vertices[:, 0]],
                               atol=1e-9)


def test_triangle_binding(tmp_path, demo):
    rig, _ = demo
    t = 100
    (tmp_path / "m.json").write_text(json.dumps({"units": "mm", "markers": [
        {"label": "a", "triangle": t, "barycentric": [0.2, 0.3, 0.5], "stable": True}]}))
    layout = MarkerLayout.load(tmp_path / "m.json", rig)
    expected = np.array([0.2, 0.3, 0.5]) @ rig.neutral[rig.triangles[t]]
    np.testing.assert_allclose(layout.marker_rig(rig).neutral[0], expected)


def test_bad_layouts(tmp_path, demo):
    rig, _ = demo
    (tmp_path / "m.json").write_text('{"markers": [{"label": "a", "vertex": 999999}]}')
    with pytest.raises(LayoutError, match="past the rig"):
        MarkerLayout.load(tmp_path / "m.json", rig)
    (tmp_path / "m.json").write_text('{"markers": [{"label": "a"}]}')
    with pytest.raises(LayoutError, match="needs 'vertex'"):
        MarkerLayout.load(tmp_path / "m.json", rig)
    (tmp_path / "m.json").write_text("{")
    with pytest.raises(LayoutError, match="m.json"):
        MarkerLayout.load(tmp_path / "m.json", rig)
